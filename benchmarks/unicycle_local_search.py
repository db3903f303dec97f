"""Is the unicycle's true cost landscape what stops PILCO? A local search on the TRUE simulator from
PILCO's own start policy.

Usage::

    .venv/bin/python benchmarks/unicycle_local_search.py [--starts 3] [--episodes 30] [--iterations 60]

PILCO starts the unicycle's squashed linear controller at ``W = 0.01 randn (2, 10)``, ``b = 0``
(``plugins/pilco/policy.py``) and improves it by a local, gradient-based search (BFGS) on its
model's prediction of the expected cost. This script takes the model out: it runs the same kind of
search on the true expected cost, the mean evaluation cost (the task's per-step cost summed over
its 67 steps, a fallen unicycle charged to the end) over ``--episodes`` episodes of the harness's
evaluator from the task's start distribution (``init=code``), the same episodes for every policy
(seeds 300000 + i: common random numbers, so the objective is a deterministic function of the
22 parameters). If even this search, with a perfect model, ends at a policy that falls, the
landscape around PILCO's start is what holds it, not the model or moment matching.

Per start (``--starts`` draws of PILCO's initial policy, generator seeds 0, 1, ...):

* ``L-BFGS-B``: scipy's, on the true objective, central finite-difference gradient (step
  ``--fd-step`` per parameter), at most ``--iterations`` iterations;
* ``CMA-ES``: :mod:`benchmarks.cmaes` from the same start (``--sigma``), a gradient-free search
  that can leave a flat region, for ``--generations`` generations.

And the segment from PILCO's start (``t = 0``) to the 0.3 m/s riding LQR (``t = 1``,
``tasks/unicycle_lqr.py``, as PILCO's squashed linear controller): the objective and the norm of its
gradient at points ``t`` of ``theta(t) = (1 - t) theta_start + t theta_lqr``, which shows how far from
the start the cost begins to fall. Every final policy is scored on ``--held-out`` new episodes
(seeds 100000 + i, those of the other unicycle benchmarks). Writes
``results/benchmarks/unicycle_local_search.md``.
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
from benchmarks.report_file import command_line, machine_line, write_report  # noqa: E402
from benchmarks.unicycle_cmaes_ceiling import ControllerClass  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.controllers import LinearController  # noqa: E402
from plugins.pilco.policy import linear_policy_from_gain  # noqa: E402
from tasks.unicycle import Unicycle  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402

SEARCH_SEED = 300_000
HELD_OUT_SEED = 100_000
LQR_SPEED = 0.3  # m/s: the riding LQR of the findings (95-100 % from init=code)


def pilco_start(seed: int, task: Unicycle) -> np.ndarray:
    """PILCO's initial linear policy ``[W.ravel(), b]`` for generator seed ``seed`` (W = 0.01 randn, b = 0)."""
    generator = torch.Generator().manual_seed(seed)
    c = LinearController.initial(task.spec.state_dim, task.spec.action_dim, scale=0.01, generator=generator)
    return np.concatenate([c.weight.detach().numpy().ravel(), c.bias.detach().numpy()])


def lqr_theta(task: Unicycle) -> np.ndarray:
    base = linear_policy_from_gain(task.spec, *riding_lqr(task, LQR_SPEED)).controller.base
    return np.concatenate([base.weight.detach().numpy().ravel(), base.bias.detach().numpy()])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--starts", type=int, default=3, help="draws of PILCO's initial policy (seeds 0, 1, ...)")
    parser.add_argument("--episodes", type=int, default=30, help="episodes of the true objective (fixed)")
    parser.add_argument("--iterations", type=int, default=60, help="L-BFGS-B iterations at most")
    parser.add_argument("--fd-step", type=float, default=1e-4, help="central finite-difference step per parameter")
    parser.add_argument("--generations", type=int, default=60, help="CMA-ES generations (0: no CMA-ES)")
    parser.add_argument("--sigma", type=float, default=0.1, help="CMA-ES initial step (parameter units)")
    parser.add_argument("--segment", type=int, default=11, help="points on the segment start -> LQR")
    parser.add_argument("--held-out", type=int, default=300, help="held-out episodes per final policy")
    parser.add_argument("--out", default=str(ROOT / "results" / "benchmarks" / "unicycle_local_search.md"))
    args = parser.parse_args(argv)
    from scipy.optimize import minimize

    from benchmarks.report_file import load_average

    load_start = load_average()
    task = Unicycle(init="code")
    u_max = np.asarray(task.spec.action_high, dtype=np.float64)
    family = ControllerClass(u_max, task.spec.state_dim, np.zeros((0, task.spec.state_dim)), np.ones(task.spec.state_dim))
    evaluator = Evaluator(task, n_episodes=args.episodes, seed=SEARCH_SEED)
    calls = [0]

    def objective(theta: np.ndarray) -> float:
        calls[0] += 1
        return evaluator(family.controller(theta)).mean_cost

    def gradient(theta: np.ndarray) -> np.ndarray:
        g = np.empty_like(theta)
        for i in range(theta.size):
            e = np.zeros_like(theta)
            e[i] = args.fd_step
            g[i] = (objective(theta + e) - objective(theta - e)) / (2 * args.fd_step)
        return g

    def held_out(theta: np.ndarray) -> tuple[float, float]:
        r = Evaluator(task, n_episodes=args.held_out, seed=HELD_OUT_SEED)(family.controller(theta))
        return r.success_rate, r.mean_cost

    started = time.perf_counter()
    theta_lqr = lqr_theta(task)
    lines = ["# The unicycle's true cost around PILCO's start: a local search with a perfect model", "",
             f"Command: `{command_line('benchmarks/unicycle_local_search.py', argv)}`  ",
             machine_line(load_start) + "  ",
             f"Objective: mean evaluation cost (of {task.spec.horizon}) over {args.episodes} fixed episodes from `init=code` "
             f"(seeds {SEARCH_SEED} + i); held-out: {args.held_out} new episodes (seeds {HELD_OUT_SEED} + i).", ""]

    rows, seg_rows = [], []
    for s in range(args.starts):
        theta0 = pilco_start(s, task)
        j0 = objective(theta0)
        # the segment start -> riding LQR
        if s == 0:
            for t in np.linspace(0.0, 1.0, args.segment):
                th = (1 - t) * theta0 + t * theta_lqr
                seg_rows.append(f"| {t:.1f} | {objective(th):.2f} | {np.linalg.norm(gradient(th)):.3g} |")
            print("\n".join(seg_rows), flush=True)
        calls[0] = 0
        t_start = time.perf_counter()
        res = minimize(objective, theta0, jac=gradient, method="L-BFGS-B", options={"maxiter": args.iterations})
        g0 = np.linalg.norm(gradient(theta0))
        sr, hc = held_out(res.x)
        rows.append(f"| {s} | L-BFGS-B | {j0:.2f} | {g0:.3g} | {res.fun:.2f} | {res.nit} ({calls[0]} J) | "
                    f"{np.linalg.norm(res.x - theta0):.3g} | {100 * sr:.0f} % ({hc:.1f}) | {time.perf_counter() - t_start:.0f} | {res.message} |")
        print(rows[-1], flush=True)
        if args.generations:
            calls[0] = 0
            t_start = time.perf_counter()
            cma = minimise(lambda z, g: objective(theta0 + z), np.zeros_like(theta0), args.sigma, args.generations, seed=s)
            theta_c = theta0 + cma.mean
            jc = objective(theta_c)
            sr, hc = held_out(theta_c)
            rows.append(f"| {s} | CMA-ES, sigma {args.sigma} | {j0:.2f} | – | {jc:.2f} | {args.generations} gen. ({calls[0]} J) | "
                        f"{np.linalg.norm(theta_c - theta0):.3g} | {100 * sr:.0f} % ({hc:.1f}) | {time.perf_counter() - t_start:.0f} | final mean |")
            print(rows[-1], flush=True)

    sr, hc = held_out(theta_lqr)
    lines += [f"Reference: the {LQR_SPEED} m/s riding LQR as PILCO's controller: objective {objective(theta_lqr):.2f}, held-out "
              f"{100 * sr:.0f} % ({hc:.1f}); distance from start 0: {np.linalg.norm(theta_lqr - pilco_start(0, task)):.3g}.", "",
              "## Searches from PILCO's start policy", "",
              "| start | search | J at start | gradient norm at start | J at end | iterations | distance moved | held-out success (cost) | wall (s) | stop |",
              "|---|---|---|---|---|---|---|---|---|---|", *rows, "",
              "## The segment from PILCO's start (t = 0, start 0) to the riding LQR (t = 1)", "",
              "| t | J | gradient norm |", "|---|---|---|", *seg_rows, "",
              f"Wall time in all: {time.perf_counter() - started:.0f} s; load average at the end {load_average():.1f}."]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
