"""Numerical robustness of PILCO over many seeds: does any seed crash with a linear-algebra error?

Runs PILCO on cart-pole for each seed with a small budget (few trials, short policy searches),
counts runs that raised, runs where a policy search failed and fell back to the previous policy
(metric ``policy_search_failed``), and trial points the line search had to back off from
(``policy_failed_evaluations``), and writes a markdown table.

    python benchmarks/robustness_pilco.py --seeds 50 --out results/benchmarks/pilco_robustness.md
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
import traceback
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, machine_line, write_report  # noqa: E402
from harness.runner import RunConfig, run  # noqa: E402
from harness.tracking import MemoryTracker  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--trials", type=int, default=4)
    parser.add_argument("--task", default="cartpole")
    parser.add_argument("--learner", default="pilco")
    parser.add_argument("--set", dest="assignments", action="append", default=None,
                        help="learner option key=value (repeatable); default: policy_max_evaluations=40 num_centres=20")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.assignments is None:
        args.assignments = ["policy_max_evaluations=40", "num_centres=20"]
    options = dict(a.split("=", 1) for a in args.assignments)

    crashes: list[tuple[int, str]] = []
    fallbacks = backoffs = trials = 0
    solved = 0
    start = time.time()
    for seed in range(args.seeds):
        tracker = MemoryTracker()
        try:
            result = run(RunConfig(args.learner, args.task, seed, learner_options=options, max_trials=args.trials, eval_episodes=3), tracker=tracker)
            solved += int(result.solved)
        except Exception as exc:  # the point of the benchmark: count every crash, keep going
            crashes.append((seed, f"{type(exc).__name__}: {exc}".splitlines()[0]))
            traceback.print_exc()
        fallbacks += int(sum(v for _, v in tracker.metrics.get("policy_search_failed", [])))
        backoffs += int(sum(v for _, v in tracker.metrics.get("policy_failed_evaluations", [])))
        trials += len(tracker.metrics.get("eval_cost", []))
        print(f"seed {seed}: {'CRASH' if crashes and crashes[-1][0] == seed else 'ok'}", flush=True)

    kinds = collections.Counter(c.split(":")[0] for _, c in crashes)
    lines = [
        f"# {args.learner} numerical robustness on {args.task}: {len(crashes)} of {args.seeds} seeds crashed",
        "",
        f"Command: `{command_line(__file__)}`  ",
        f"{machine_line()} One torch thread; wall {time.time() - start:.0f} s.",
        "",
        "| seeds | trials run | runs that crashed | policy searches that fell back to the previous policy | line-search back-offs (non-finite J) | solved within the budget |",
        "|---|---|---|---|---|---|",
        f"| {args.seeds} | {trials} | {len(crashes)} | {fallbacks} | {backoffs} | {solved} |",
        "",
    ]
    if crashes:
        lines += ["Crashes:", ""] + [f"- seed {s}: {msg}" for s, msg in crashes] + ["", f"By type: {dict(kinds)}"]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
