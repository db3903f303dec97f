"""Where do solving policies sit on MC-PILCO's cost? Stored policies scored with the task's cost and the paper's.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/paper_cost_of_policies.py --runs RUN_ID [RUN_ID ...]
        [--trial K] [--horizon H] [--episodes 20] [--seed 777] [--tracking-uri URI] [--out FILE]

For each stored ``pilco``, ``pilco-mean`` or ``mc-pilco`` run on a task for which the MC-PILCO paper
defines a planning cost (:data:`plugins.mc_pilco.costs.PAPER_COSTS`), the policy handed over at trial
``--trial`` (default: the run's last) runs ``--episodes`` test episodes of the task (the run's own task
options, the horizon replaced by ``--horizon`` where given, so that runs of different horizons compare;
the same initial states for every policy). Each episode is scored with the task's cost and with the
paper's cost, both summed over the states after the first, as J sums them.

Reading: an ``mc-pilco`` search with ``cost=paper`` that settles at a J well above what solving
policies score on the same cost sits in a local optimum of its objective; one that settles near it
has found what the cost asks for.
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
from benchmarks.swingup_failure_modes import add_test_arguments  # noqa: E402
from harness.statistics import wilson_interval  # noqa: E402
from harness.discovery import load_task  # noqa: E402
from harness.errors import CheckpointError, exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.mc_pilco.costs import PAPER_COSTS  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


def score_policy(run: SavedPilcoRun, trial: int | None, horizon: int | None, episodes: int, seed: int) -> dict:
    """One run's policy on test episodes: ``trial``, ``success`` (count), ``task`` and ``paper`` (per-episode
    summed costs, arrays), ``horizon``."""
    name = run.params["task"]
    if name not in PAPER_COSTS:
        raise CheckpointError(f"run {run.run_id} is on {name!r}: the MC-PILCO paper defines no cost for it "
                              f"(tasks with one: {', '.join(sorted(PAPER_COSTS))})")
    trials = run.policy_trials()
    if not trials:
        raise CheckpointError(f"run {run.run_id} has no stored policy")
    trial = trials[-1] if trial is None else trial
    if trial not in trials:
        raise CheckpointError(f"run {run.run_id} has no policy of trial {trial} (it has {trials[0]}..{trials[-1]})")
    task = run.task if horizon is None else load_task(name)(**{**run.task.options, "horizon": horizon})
    evaluator = Evaluator(task, n_episodes=episodes, seed=seed)
    try:
        result = evaluator(run.policy(trial))
    finally:
        evaluator.close()
    states = [np.asarray(ep.states)[1:] for ep in result.episodes]
    return {"trial": trial, "horizon": task.spec.horizon, "success": sum(bool(task.success(ep)) for ep in result.episodes),
            "task": np.array([float(np.sum(task.spec.cost(s))) for s in states]),
            "paper": np.array([float(np.sum(PAPER_COSTS[name](s))) for s in states])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument("--trial", type=int, default=None, help="the policy of this trial (default: each run's last)")
    parser.add_argument("--horizon", type=int, default=None, help="test episodes of this many steps (default: the run's task's)")
    add_test_arguments(parser, episodes=20)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    start = time.perf_counter()
    lines = ["# Stored policies on the task's cost and on MC-PILCO's", "",
             f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
             f"Test: {args.episodes} episodes per policy (seed {args.seed}, the same initial states for every policy); costs "
             "summed over the states after the first. MC-PILCO's cost: `plugins/mc_pilco/costs.py`.", "",
             "| run | learner | planning cost | seed | trial | H | success (95 % CI) | task cost, mean | MC-PILCO cost, mean (min-max) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for run_id in args.runs:
        with SavedPilcoRun(run_id, args.tracking_uri) as run:
            found = score_policy(run, args.trial, args.horizon, args.episodes, args.seed)
            params = run.params
        low, high = wilson_interval(found["success"], args.episodes)
        paper = found["paper"]
        planned = "MC-PILCO's" if params.get("learner.cost") == "paper" else "task's"
        lines.append(f"| `{run_id[:8]}` | {params['learner']} | {planned} | {params.get('seed', '?')} | {found['trial']} | {found['horizon']} "
                     f"| {found['success']}/{args.episodes} ({100 * low:.0f}-{100 * high:.0f} %) | {found['task'].mean():.2f} "
                     f"| {paper.mean():.2f} ({paper.min():.2f}-{paper.max():.2f}) |")
        print(f"{run_id[:8]} trial {found['trial']}: {found['success']}/{args.episodes}, task {found['task'].mean():.2f}, "
              f"MC-PILCO {paper.mean():.2f}", flush=True)
    lines += ["", f"Wall time {time.perf_counter() - start:.0f} s."]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
