"""Does a second thread speed up one PILCO J + dJ? Torch's intra-op threads and the compiled
kernel's pair-group threads, separately and together, at the real tasks' sizes.

Usage::

    .venv/bin/python benchmarks/threads_objective.py [--threads 2] [--rounds 3]

For each configuration of ``benchmarks/task_objectives.py`` and each (torch threads, pair-group
threads) in {1, N}^2: median wall and CPU time of 3 J + dJ evaluations after a warm-up, over
``--rounds`` alternating rounds. Run it on an otherwise idle machine (the load is printed). Writes
``results/benchmarks/threads_objective.md``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from benchmarks.task_objectives import TASK_CONFIGS, task_objective  # noqa: E402
from plugins.pilco.moments import MomentMatchingGP  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "threads_objective.md")
    args = parser.parse_args(argv)
    load = load_average()
    combos = [(1, 1), (1, args.threads), (args.threads, 1), (args.threads, args.threads)]
    lines = ["# One PILCO J + dJ with one or more threads", "", f"Command: `{command_line(__file__, argv)}`  ", f"{machine_line(load)}  ",
             f"Median over {args.rounds} alternating rounds of 3 evaluations after a warm-up; the kernel: `auto`.", "",
             "| configuration | torch threads | pair-group threads | wall ms | CPU ms | wall speed-up over 1/1 |", "|---|---|---|---|---|---|"]
    for name, (task, options, n, horizon) in TASK_CONFIGS.items():
        objective = task_objective(task, options, n, horizon)
        theta = objective.get_flat()
        times: dict[tuple[int, int], list[tuple[float, float]]] = {c: [] for c in combos}
        for _ in range(args.rounds):
            for torch_threads, pair_threads in combos:
                torch.set_num_threads(torch_threads)
                objective.dynamics = MomentMatchingGP(objective.posterior, threads=pair_threads)
                objective(theta)
                wall, cpu = time.perf_counter(), time.process_time()
                for _ in range(3):
                    objective(theta)
                times[torch_threads, pair_threads].append(((time.perf_counter() - wall) / 3, (time.process_time() - cpu) / 3))
        base = statistics.median(w for w, _ in times[1, 1])
        for combo in combos:
            wall = statistics.median(w for w, _ in times[combo])
            cpu = statistics.median(c for _, c in times[combo])
            lines.append(f"| {name} | {combo[0]} | {combo[1]} | {wall * 1e3:.0f} | {cpu * 1e3:.0f} | {base / wall:.2f} |")
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
