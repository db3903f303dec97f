"""The best policy CMA-ES finds on the true unicycle: the ceiling for PILCO's linear controller, and for a
nonlinear one.

Usage::

    .venv/bin/python benchmarks/unicycle_cmaes_ceiling.py [--init paper] [--generations 100] [--episodes 100]
    .venv/bin/python benchmarks/unicycle_cmaes_ceiling.py --controller linear+rbf [--centres 40] [--generations 100]

``--controller linear`` (default): PILCO's squashed linear controller on the unicycle,
``u = u_max squash(W x + b)`` (``W (2, 10)``, ``b (2,)``: 22 parameters), started at the best riding
LQR of ``benchmarks/unicycle_linear_ceiling.py`` (1.5 m/s).

``--controller linear+rbf``: the same with a sum of Gaussian bumps added before the squashing,
``u = u_max squash(W x + b + sum_i t_i exp(-|(x - c_i) / l|^2 / 2))`` (``t_i (2,)`` for ``--centres``
centres ``c_i``: 22 + 2 N parameters), a nonlinear controller that contains the linear one. It starts
at the linear search's final mean (``--start``, the ``.npz`` the linear search writes) with every
``t_i = 0``, i.e. at exactly that linear policy. The centres are states that policy visits (50
episodes, seeds 500000 + i, drawn at random among their observations, seed 0), the length-scales
``l`` the spread of those observations per entry (``--length-scale`` times their standard deviation).
Because the search starts at the linear optimum and can keep the bumps at 0, what it adds measures
what nonlinearity buys, a lower bound on the nonlinear ceiling.

Both are searched by CMA-ES (:mod:`benchmarks.cmaes`) directly on the true simulator from the start
distribution ``--init`` (the paper's Sigma0 = 0.25^2 I by default). Each candidate is scored on
``--episodes`` episodes of the harness's evaluator (the task's success rule, measurement noise on)
shared by the generation and new in each generation (seeds 300000 + 1000 g): score = failure rate +
0.001 * mean evaluation cost (the cost breaks ties between equal rates). The search applies the
controller in numpy (:class:`NumpyController`, equal to PILCO's torch policy to 1e-12; the test
checks); each parameter is scaled by its own magnitude (targets ``t_i`` by ``--target-scale``: with 40
bumps at 1 standard deviation the bumps' values at a visited state have a root sum of squares of ~1, at 3
standard deviations ~3.9, so 1/3.9 there gives the first steps the same size). The start, the best
candidate of the search (winner of a noisy score) and the search's final mean are then evaluated on
1000 held-out episodes (seeds 100000 + i, those of the LQR table), the linear ones through PILCO's
own policy class. Writes ``results/benchmarks/unicycle_cmaes_ceiling_<init>[_rbf].md`` and the
policies' parameters beside it (``.npz``); the table is rewritten every 10 generations, so a stopped
search leaves its best so far.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
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
SEARCH_SEED = 300_000
CENTRE_SEED = 500_000


def policy_of(task: Unicycle, theta: np.ndarray) -> PilcoPolicy:
    """PILCO's squashed linear controller with ``theta = [W.ravel(), b]``."""
    f = task.spec.action_dim
    return linear_policy(task.spec, theta[:-f].reshape(f, -1), theta[-f:])


def theta_of(policy: PilcoPolicy) -> np.ndarray:
    """``[W.ravel(), b]`` of a squashed linear :class:`PilcoPolicy`."""
    base = policy.controller.base
    return np.concatenate([base.weight.detach().numpy().ravel(), base.bias.detach().numpy()])


@dataclass(frozen=True)
class NumpyController:
    """``u = u_max (9 sin z + sin 3z) / 8`` with ``z = W x + b + sum_i t_i exp(-|(x - c_i) * inv_l|^2 / 2)``.

    The unicycle's policy sees the raw observation ``x (10,)``; ``W (F, 10)``, ``b (F,)``, ``u_max (F,)``,
    ``centres (N, 10)``, ``inv_length (10,)``, ``targets (N, F)`` (``N = 0``: PILCO's linear controller).
    """

    W: np.ndarray
    b: np.ndarray
    u_max: np.ndarray
    centres: np.ndarray
    inv_length: np.ndarray
    targets: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        z = self.W @ x + self.b
        if len(self.targets):
            d = (x - self.centres) * self.inv_length
            z = z + np.exp(-0.5 * np.einsum("nd,nd->n", d, d)) @ self.targets
        return self.u_max * (9.0 * np.sin(z) + np.sin(3.0 * z)) / 8.0


@dataclass(frozen=True)
class ControllerClass:
    """Maps a parameter vector ``[W.ravel(), b, targets.ravel()]`` to a controller; the bumps are fixed."""

    u_max: np.ndarray
    obs_dim: int
    centres: np.ndarray
    inv_length: np.ndarray

    @property
    def size(self) -> int:
        f = len(self.u_max)
        return f * self.obs_dim + f + f * len(self.centres)

    def controller(self, theta: np.ndarray) -> NumpyController:
        f, d = len(self.u_max), self.obs_dim
        W, b, t = theta[: f * d].reshape(f, d), theta[f * d : f * d + f], theta[f * d + f :].reshape(-1, f)
        return NumpyController(W, b, self.u_max, self.centres, self.inv_length, t)


def bumps_around(task: Unicycle, theta_linear: np.ndarray, n: int, length_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (n, D), inv_length (D,))``: ``n`` observations the linear policy visits (50 episodes), and
    1 / (``length_scale`` x their standard deviation per entry)."""
    episodes = Evaluator(task, n_episodes=50, seed=CENTRE_SEED)(policy_of(task, theta_linear)).episodes
    visited = np.concatenate([ep.observations for ep in episodes])
    centres = visited[np.random.default_rng(0).choice(len(visited), size=n, replace=False)]
    return centres, 1.0 / (length_scale * np.maximum(visited.std(axis=0), 1e-3))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--init", default="paper", choices=("paper", "code"))
    parser.add_argument("--controller", default="linear", choices=("linear", "linear+rbf"))
    parser.add_argument("--start", type=Path, default=None,
                        help="linear+rbf: the linear search's .npz (default: results/benchmarks/unicycle_cmaes_ceiling_<init>.npz)")
    parser.add_argument("--centres", type=int, default=40, help="linear+rbf: number of bumps")
    parser.add_argument("--length-scale", type=float, default=1.0, help="linear+rbf: bump width in standard deviations")
    parser.add_argument("--target-scale", type=float, default=1.0,
                        help="linear+rbf: the bumps' targets in units of this (wider bumps overlap more: a smaller unit keeps the first steps as small)")
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--episodes", type=int, default=100, help="episodes per candidate (shared within a generation)")
    parser.add_argument("--popsize", type=int, default=12)
    parser.add_argument("--sigma", type=float, default=0.05, help="initial step, relative to each coordinate's magnitude")
    parser.add_argument("--held-out", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=None, help="markdown file (the .npz is written beside it)")
    args = parser.parse_args(argv)
    rbf = args.controller == "linear+rbf"
    folder = ROOT / "results" / "benchmarks"
    out = args.out or folder / f"unicycle_cmaes_ceiling_{args.init}{'_rbf' if rbf else ''}.md"
    torch.set_num_threads(1)
    task = Unicycle(init=args.init)
    u_max = np.asarray(task.spec.action_high, dtype=np.float64)
    f = task.spec.action_dim
    if rbf:
        start_file = args.start or folder / f"unicycle_cmaes_ceiling_{args.init}.npz"
        if not start_file.is_file():
            parser.error(f"--start {start_file}: no such file; run the linear search first "
                         f"(python benchmarks/unicycle_cmaes_ceiling.py --init {args.init}), it writes it")
        linear = np.load(start_file)["mean"]
        centres, inv_length = bumps_around(task, linear, args.centres, args.length_scale)
        start_name = f"the linear search's final mean (`{start_file.name}`)"
    else:
        linear = theta_of(linear_policy_from_gain(task.spec, *riding_lqr(task, 1.5)))
        centres, inv_length = np.zeros((0, task.spec.state_dim)), np.ones(task.spec.state_dim)
        start_name = "riding LQR 1.5 m/s"
    family = ControllerClass(u_max, task.spec.state_dim, centres, inv_length)
    theta0 = np.concatenate([linear, np.zeros(f * len(centres))])
    scale = np.concatenate([np.maximum(np.abs(linear), 0.1 * np.abs(linear).mean()), np.full(f * len(centres), args.target_scale)])
    evaluators: dict[int, Evaluator] = {}

    def score(z: np.ndarray, generation: int) -> float:
        if generation not in evaluators:
            evaluators.clear()
            evaluators[generation] = Evaluator(task, n_episodes=args.episodes, seed=SEARCH_SEED + 1000 * generation)
        result = evaluators[generation](family.controller(theta0 + scale * z))
        return (1.0 - result.success_rate) + 0.001 * result.mean_cost

    started = time.perf_counter()

    def held_out(theta: np.ndarray):
        policy = family.controller(theta) if rbf else policy_of(task, theta)
        return Evaluator(task, n_episodes=args.held_out, seed=HELD_OUT_SEED)(policy)

    def report(result, final: bool) -> None:
        rows = [f"| {g} | {100 * (1 - min(best, 1.0)):.0f} % (score {best:.3f}) | {mean:.3f} | {sigma:.3f} |"
                for g, best, mean, sigma in result.trace[:: max(1, len(result.trace) // 25)]]
        what = (f"PILCO's squashed linear controller plus {len(centres)} Gaussian bumps before the squashing "
                f"({family.size} parameters; width {args.length_scale} x the spread of the visited observations, targets in units of "
                f"{args.target_scale})"
                if rbf else f"PILCO's squashed linear controller ({family.size} parameters)")
        lines = [f"# Unicycle (`init={args.init}`): the best {'linear + RBF' if rbf else 'linear'} policy CMA-ES finds on the true simulator", "",
                 f"Command: `{command_line(__file__, argv)}`  ",
                 f"CMA-ES over {what}, {args.popsize} candidates a generation, "
                 f"{args.episodes} shared episodes per generation (new each generation), score = failure rate + 0.001 x mean cost; "
                 f"start: {start_name}; {result.generations} generations, {result.evaluations} candidates, "
                 f"{time.perf_counter() - started:.0f} s wall.", ""]
        if final:
            thetas = {"start": theta0, "best": theta0 + scale * result.best_x, "mean": theta0 + scale * result.mean}
            np.savez(out.with_suffix(".npz"), **thetas, centres=centres, inv_length=inv_length, u_max=u_max)
            evals = ((f"start: {start_name}", held_out(thetas["start"])), ("CMA-ES: best candidate", held_out(thetas["best"])),
                     ("CMA-ES: final mean", held_out(thetas["mean"])))
            lines += [f"Held-out evaluation ({args.held_out} episodes, seeds {HELD_OUT_SEED} + i, as in `unicycle_linear_ceiling.md`; "
                      f"parameters in `{out.with_suffix('.npz').name}`):", "",
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
