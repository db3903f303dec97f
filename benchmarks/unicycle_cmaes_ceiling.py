"""The best linear policy CMA-ES finds on the true unicycle: the ceiling for PILCO's controller class.

Usage::

    .venv/bin/python benchmarks/unicycle_cmaes_ceiling.py [--init paper] [--generations 100] [--episodes 100]

PILCO's squashed linear controller on the unicycle, ``u = u_max squash(W x + b)`` (``W (2, 10)``,
``b (2,)``: 22 parameters), searched by CMA-ES (:mod:`benchmarks.cmaes`) directly on the true
simulator from the start distribution ``--init`` (the paper's Sigma0 = 0.25^2 I by default). Each
candidate is scored on ``--episodes`` episodes of the harness's evaluator (the task's success rule,
measurement noise on) shared by the generation and new in each generation (seeds 300000 + 1000 g):
score = failure rate + 0.001 * mean evaluation cost (the cost breaks ties between equal rates).
The search starts from the best riding LQR of ``benchmarks/unicycle_linear_ceiling.py`` (1.5 m/s),
each coordinate scaled by its own magnitude. The start, the best candidate of the search (winner of a
noisy score) and the search's final mean are then
evaluated on 1000 held-out episodes (seeds 100000 + i, those of the LQR table). Writes
``results/benchmarks/unicycle_cmaes_ceiling_<init>.md``; the table is rewritten every 10
generations, so a stopped search leaves its best so far.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.cmaes import minimise  # noqa: E402
from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.policy import PilcoPolicy, linear_policy, linear_policy_from_gain  # noqa: E402
from tasks.unicycle import Unicycle  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402

HELD_OUT_SEED = 100_000


def policy_of(task: Unicycle, theta: np.ndarray) -> PilcoPolicy:
    """PILCO's squashed linear controller with ``theta = [W.ravel(), b]``."""
    f = task.spec.action_dim
    return linear_policy(task.spec, theta[:-f].reshape(f, -1), theta[-f:])


def theta_of(policy: PilcoPolicy) -> np.ndarray:
    base = policy.controller.base
    return np.concatenate([base.weight.detach().numpy().ravel(), base.bias.detach().numpy()])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--init", default="paper", choices=("paper", "code"))
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--episodes", type=int, default=100, help="episodes per candidate (shared within a generation)")
    parser.add_argument("--popsize", type=int, default=12)
    parser.add_argument("--sigma", type=float, default=0.05, help="initial step, relative to each coordinate's magnitude")
    parser.add_argument("--held-out", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    out = args.out or ROOT / "results" / "benchmarks" / f"unicycle_cmaes_ceiling_{args.init}.md"
    torch.set_num_threads(1)
    task = Unicycle(init=args.init)
    start_policy = linear_policy_from_gain(task.spec, *riding_lqr(task, 1.5))
    theta0 = theta_of(start_policy)
    scale = np.maximum(np.abs(theta0), 0.1 * np.abs(theta0).mean())
    evaluators: dict[int, Evaluator] = {}

    def score(z: np.ndarray, generation: int) -> float:
        if generation not in evaluators:
            evaluators.clear()
            evaluators[generation] = Evaluator(task, n_episodes=args.episodes, seed=300_000 + 1000 * generation)
        result = evaluators[generation](policy_of(task, theta0 + scale * z))
        return (1.0 - result.success_rate) + 0.001 * result.mean_cost

    started = time.perf_counter()

    def held_out(theta: np.ndarray):
        return Evaluator(task, n_episodes=args.held_out, seed=HELD_OUT_SEED)(policy_of(task, theta))

    def report(result, final: bool) -> None:
        rows = [f"| {g} | {100 * (1 - min(best, 1.0)):.0f} % (score {best:.3f}) | {mean:.3f} | {sigma:.3f} |"
                for g, best, mean, sigma in result.trace[:: max(1, len(result.trace) // 25)]]
        lines = [f"# Unicycle (`init={args.init}`): the best linear policy CMA-ES finds on the true simulator", "",
                 f"Command: `{command_line(__file__, argv)}`  ",
                 f"CMA-ES over PILCO's squashed linear controller (22 parameters), {args.popsize} candidates a generation, "
                 f"{args.episodes} shared episodes per generation (new each generation), score = failure rate + 0.001 x mean cost; "
                 f"start: the 1.5 m/s riding LQR; {result.generations} generations, {result.evaluations} candidates, "
                 f"{time.perf_counter() - started:.0f} s wall.", ""]
        if final:
            evals = (("start: riding LQR 1.5 m/s", held_out(theta0)), ("CMA-ES: best candidate", held_out(theta0 + scale * result.best_x)),
                     ("CMA-ES: final mean", held_out(theta0 + scale * result.mean)))
            lines += [f"Held-out evaluation ({args.held_out} episodes, seeds {HELD_OUT_SEED} + i, as in `unicycle_linear_ceiling.md`):", "",
                      "| policy | success | falls | cost |", "|---|---|---|---|"]
            for name, ev in evals:
                falls = np.mean([ep.terminated for ep in ev.episodes])
                lines.append(f"| {name} | {100 * ev.success_rate:.1f} % | {100 * falls:.1f} % | {ev.mean_cost:.1f} |")
            lines += ["", "The ICML paper reports ~93 % success for PILCO's learned linear policy from Sigma0 = 0.25^2 I.", ""]
            print("\n".join(lines[-8:]), flush=True)
        lines += ["Search trace (training episodes; the best candidate of each generation is scored on that generation's episodes only):", "",
                  "| generation | best of generation: success (score) | mean score | sigma |", "|---|---|---|---|", *rows]
        write_report(lines, out)

    def progress(g: int, result) -> None:
        _, best, mean, sigma = result.trace[-1]
        print(f"generation {g}: best {best:.3f} mean {mean:.3f} sigma {sigma:.3f} ({time.perf_counter() - started:.0f} s)", flush=True)
        if (g + 1) % 10 == 0:
            report(result, final=False)

    result = minimise(score, np.zeros_like(theta0), args.sigma, args.generations, popsize=args.popsize, seed=0, callback=progress)
    report(result, final=True)


if __name__ == "__main__":
    main()
