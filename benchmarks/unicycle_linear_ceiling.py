"""What a linear policy can reach on the unicycle: riding LQRs as PILCO's squashed linear controller.

Usage::

    .venv/bin/python benchmarks/unicycle_linear_ceiling.py [--episodes 1000] [--speeds 0.3 0.5 1 1.5]

For each start distribution (task option ``init``: ``paper`` = 0.25^2 I on the 12 ODE states,
``code`` = the reference code's) and each riding speed, the discrete LQR about riding straight
(:func:`tasks.unicycle_lqr.riding_lqr`) is mapped to PILCO's linear controller with trapezoid
squashing (:func:`plugins.pilco.policy.linear_policy_from_gain`) and run by the harness's
evaluator (the task's success rule; cost summed over the 67-step horizon, a fall held to the end)
on ``--episodes`` fresh episodes with measurement noise. A zero-torque row shows the fall baseline.
Writes ``results/benchmarks/unicycle_linear_ceiling.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.policy import linear_policy_from_gain  # noqa: E402
from tasks.unicycle import Unicycle  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.3, 0.5, 1.0, 1.5])
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "unicycle_linear_ceiling.md")
    args = parser.parse_args(argv)
    rows = []
    for init in ("code", "paper"):
        task = Unicycle(init=init)
        policies = [("zero torque", lambda obs: np.zeros(2))]
        policies += [(f"riding LQR, {v:g} m/s", linear_policy_from_gain(task.spec, *riding_lqr(task, v))) for v in args.speeds]
        for name, policy in policies:
            start = time.perf_counter()
            evaluator = Evaluator(task, n_episodes=args.episodes, seed=100_000)
            result = evaluator(policy)
            falls = np.mean([ep.terminated for ep in result.episodes])
            rows.append((init, name, result.success_rate, falls, result.mean_cost))
            print(f"{init:5s} {name:22s} success {100 * result.success_rate:5.1f} %  falls {100 * falls:5.1f} %  "
                  f"cost {result.mean_cost:5.1f}  ({time.perf_counter() - start:.0f} s)", flush=True)
    lines = [
        "# Unicycle: what a linear policy reaches (riding LQRs as PILCO's squashed linear controller)", "",
        f"Command: `{command_line(__file__, argv)}`  ",
        f"{args.episodes} evaluation episodes per row (seeds 100000 + i, measurement noise on), the task's success rule "
        "(no fall in 10 s and the top within 0.10 m of upright at the end); cost = evaluation cost over the 67-step "
        "horizon with a fall held to the end (max 67). The ICML paper reports ~93 % success for PILCO's learned "
        "linear policy from Sigma0 = 0.25^2 I.", "",
        "| start (`init`) | policy | success | falls | cost |", "|---|---|---|---|---|",
    ]
    lines += [f"| {i} | {n} | {100 * s:.1f} % | {100 * f:.1f} % | {c:.1f} |" for i, n, s, f, c in rows]
    lines += ["", "Upright and at rest neither torque enters the roll acceleration to first order (tests in "
              "`tests/tasks/test_unicycle.py`), so a linear policy can only balance about a moving equilibrium: "
              "the LQRs ride straight at the given speed (`tasks/unicycle_lqr.py`)."]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
