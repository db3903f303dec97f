"""How a swing-up policy fails: its success over many test episodes, and what the failures do.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/swingup_failure_modes.py --runs RUN_ID [RUN_ID ...]
        --trials 20 25 [--episodes 100] [--seed 777] [--tracking-uri URI] [--out FILE]

For each PILCO (or mc-pilco) run on a swing-up task (``cartpole``, ``double-pendulum``: tasks with a tip distance
and a "within ``success_radius`` for ``success_steps`` steps" rule) and each of ``--trials``, the
policy handed over at that trial is run on ``--episodes`` test episodes from the task's initial
distribution (the same initial states for every policy). Reported beside the run's own evaluation
(``eval_episodes`` per hand-over, 10 by default, ``eval_success_rate``; "solved" needs 90 % of them):

* success over the test episodes, with a Wilson 95 % interval;
* each failure classed by what the tip did: **never reached** the success radius; **reached, fell
  away** (came within the radius, left it before holding ``success_steps`` steps, and was outside at
  the end); **reached, cut off** (inside at the episode's end without a long enough hold: the
  trial ended first);
* the step at which the tip first came within the radius (quartiles over the episodes that did),
  and the median tip distance at each quarter of the episode.
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

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import CheckpointError, exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from harness.task import Episode  # noqa: E402
from harness.statistics import wilson_interval  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402

#: failure classes, in table order
OUTCOMES = ("success", "never reached", "reached, fell away", "reached, cut off")


def add_test_arguments(parser: argparse.ArgumentParser, episodes: int = 100) -> None:
    """The options of a benchmark that tests a stored run's policies on the real task: ``--episodes``
    (default ``episodes``), ``--seed`` (of the test episodes' initial states), ``--tracking-uri``, ``--out``."""
    parser.add_argument("--episodes", type=int, default=episodes)
    parser.add_argument("--seed", type=int, default=777, help="seed of the test episodes' initial states")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: print only)")


def outcome(distances: np.ndarray, radius: float, solved: bool) -> str:
    """The class of one episode from its per-step tip distances ``(T,)`` (m) and the task's verdict."""
    if solved:
        return "success"
    inside = distances <= radius
    if not inside.any():
        return "never reached"
    return "reached, cut off" if inside[-1] else "reached, fell away"


def describe(task, episodes: list[Episode]) -> dict:
    """Outcome counts, first-entry step quartiles and the median tip distance per quarter."""
    distances = np.array([task.tip_distance(ep.states) for ep in episodes])  # (N, T+1)
    counts = dict.fromkeys(OUTCOMES, 0)
    entries = []
    for ep, d in zip(episodes, distances):
        counts[outcome(d, task.success_radius, task.success(ep))] += 1
        inside = np.flatnonzero(d <= task.success_radius)
        if inside.size:
            entries.append(int(inside[0]))
    steps = distances.shape[1] - 1
    quarters = [round(q * steps / 4) for q in range(5)]
    return {
        "counts": counts,
        "entry_quartiles": tuple(np.percentile(entries, [25, 50, 75])) if entries else None,
        "median_distance": [(s, float(np.median(distances[:, s]))) for s in quarters],
        "steps": steps,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument("--trials", type=int, nargs="+", required=True)
    add_test_arguments(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    start = time.perf_counter()

    rows, task_name, radius, hold, steps = [], None, None, None, None
    names: list[str] = []  # the runs' learners, in order of first appearance
    for run_id in args.runs:
        with SavedPilcoRun(run_id, args.tracking_uri, task=task_name) as run:
            task = run.task
            if run.params["learner"] not in names:
                names.append(run.params["learner"])
            if not hasattr(task, "tip_distance"):
                raise CheckpointError(f"run {run_id} is on {run.params['task']!r}, not a swing-up task with a tip distance")
            task_name, radius, hold = run.params["task"], task.success_radius, task.success_steps
            evaluator = Evaluator(task, n_episodes=args.episodes, seed=args.seed)
            logged = run.metric("eval_success_rate")
            available = set(run.policy_trials())
            n_eval = int(run.params.get("eval_episodes", 10))
            for trial in args.trials:
                if trial not in available:
                    print(f"run {run_id[:8]}: no policy of trial {trial}; skipped", flush=True)
                    continue
                found = describe(task, evaluator(run.policy(trial)).episodes)
                steps = found["steps"]
                own = None if trial not in logged else f"{round(n_eval * logged[trial])} of {n_eval}"
                rows.append((run_id[:8], run.params.get("seed", "?"), trial, own, found))
                c = found["counts"]
                print(f"{run_id[:8]} trial {trial}: {c['success']} of {args.episodes} ({c})", flush=True)
            evaluator.close()

    if not rows:
        sys.exit("no policy tested: none of the runs has a policy of the asked trials")
    quarter_steps = [s for s, _ in rows[0][4]["median_distance"]]
    learners = ", ".join(names)
    lines = [
        f"# How swing-up policies fail ({task_name}: {learners})", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Test: {args.episodes} episodes of {steps} steps from the task's initial distribution (seed {args.seed}, the same "
        f"initial states for every policy). Success: tip within {radius * 100:.0f} cm of upright for {hold} consecutive steps. "
        f"Wall time {time.perf_counter() - start:.0f} s.", "",
        "| run | seed | trial | run's evaluation | success (95 % CI) | never reached | reached, fell away "
        "| reached, cut off | first entry step (quartiles) | median tip distance (m) at steps "
        + ", ".join(map(str, quarter_steps)) + " |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run_id, seed, trial, own, found in rows:
        c, n = found["counts"], args.episodes
        low, high = wilson_interval(c["success"], n)
        entry = "–" if found["entry_quartiles"] is None else "{:.0f} / {:.0f} / {:.0f}".format(*found["entry_quartiles"])
        dist = ", ".join(f"{d:.2f}" for _, d in found["median_distance"])
        lines.append(f"| `{run_id}` | {seed} | {trial} | {own or '–'} | {c['success']}/{n} ({100 * low:.0f}–{100 * high:.0f} %) "
                     f"| {c['never reached']} | {c['reached, fell away']} | {c['reached, cut off']} | {entry} | {dist} |")
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
