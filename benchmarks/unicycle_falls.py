"""Where and when a unicycle policy falls: fall rate by the size of each initial state entry, and fall times.

Usage::

    .venv/bin/python benchmarks/unicycle_falls.py --policy results/benchmarks/unicycle_cmaes_ceiling_paper.npz [--init paper]

Loads a policy the CMA-ES search wrote (``benchmarks/unicycle_cmaes_ceiling.py``: its final mean,
``--which``, linear or linear + RBF), runs it on ``--episodes`` held-out episodes (seeds 100000 + i,
those of the ceiling tables) with the harness's evaluator, and writes
``results/benchmarks/unicycle_falls_<policy file's stem>.md``: the success rate, when the falls happen
(steps of dt = 0.15 s), and for each of the 10 observation entries the fall rate of the episodes whose
initial ``|x_0|`` is among the largest fifth against the other four fifths. A start distribution that
holds states no controller of the class can catch shows up as falls concentrated in the first steps and
in the tail of a few entries.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from benchmarks.unicycle_cmaes_ceiling import HELD_OUT_SEED, ControllerClass  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from tasks.unicycle import STATE_NAMES, Unicycle  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", type=Path, required=True, help="an .npz written by benchmarks/unicycle_cmaes_ceiling.py")
    parser.add_argument("--which", default="mean", choices=("start", "best", "mean"))
    parser.add_argument("--init", default="paper", choices=("paper", "code"))
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if not args.policy.is_file():
        parser.error(f"--policy {args.policy}: no such file; benchmarks/unicycle_cmaes_ceiling.py writes one beside its table")
    saved = np.load(args.policy)
    out = args.out or ROOT / "results" / "benchmarks" / f"unicycle_falls_{args.policy.stem}.md"
    task = Unicycle(init=args.init)
    family = ControllerClass(saved["u_max"], task.spec.state_dim, saved["centres"], saved["inv_length"])
    result = Evaluator(task, n_episodes=args.episodes, seed=HELD_OUT_SEED)(family.controller(saved[args.which]))
    fell = np.array([ep.terminated for ep in result.episodes])
    steps = np.array([ep.steps for ep in result.episodes])
    x0 = np.abs(np.array([ep.observations[0] for ep in result.episodes]))
    lines = [f"# Unicycle (`init={args.init}`): where and when `{args.policy.name}` ({args.which}) falls", "",
             f"Command: `{command_line(__file__, argv)}`  ",
             f"{args.episodes} held-out episodes (seeds {HELD_OUT_SEED} + i): success {100 * result.success_rate:.1f} %, "
             f"falls {100 * fell.mean():.1f} % ({fell.sum()} episodes).", ""]
    if fell.any():
        quantiles = np.percentile(steps[fell], [10, 25, 50, 75, 90])
        lines += ["Step of the fall (dt = 0.15 s), quantiles over the falling episodes: "
                  + ", ".join(f"{q}: {v:.0f}" for q, v in zip(("10 %", "25 %", "50 %", "75 %", "90 %"), quantiles))
                  + f"; {100 * np.mean(steps[fell] <= 6):.0f} % of the falls within the first 6 steps (0.9 s).", ""]
    lines += ["| entry | fall rate, largest fifth of initial abs value | fall rate, the rest |", "|---|---|---|"]
    for i, name in enumerate(STATE_NAMES):
        top = x0[:, i] > np.percentile(x0[:, i], 80)
        lines.append(f"| {name} | {100 * fell[top].mean():.0f} % | {100 * fell[~top].mean():.0f} % |")
    write_report(lines, out)


if __name__ == "__main__":
    main()
