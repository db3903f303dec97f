"""Is it the model or the objective? A run's predicted J beside the cost its policy really incurred.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/planning_cost_check.py --runs RUN_ID [RUN_ID ...]
        [--tracking-uri URI] [--out FILE]

For each stored ``pilco``, ``pilco-mean`` or ``mc-pilco`` run, trial by trial: the J its policy search
ended with (``J_after``, the model's prediction of the planning cost over the planning horizon), and
the cost the same policy's next trial really incurred, computed from the recorded states with the
planning cost (its width, its horizon) and with the task's own cost (the task's width, the task's
horizon); an episode that ended early (a fall) holds its last cost for the steps it did not take, as
evaluations score it. The run's evaluation cost is shown beside them.

Reading: where the realised planning cost agrees with the prediction while the task's cost stays high,
the model is right and the search did what it was asked; the objective (width, horizon) does not ask
for the task. Where the prediction is far below what was realised, the policy exploits the model's
errors.

The planning width is the run's ``cost_width`` metric at that trial (``mc-pilco`` logs it; it narrows
with ``cost_narrowing``), else its ``learner.cost_width`` param, else its ``pilco_settings.json``'s
(``pilco`` runs), else the task's; an ``mc-pilco`` run with ``cost=paper`` planned with MC-PILCO's cost
for the task (:mod:`plugins.mc_pilco.costs`), which has no width. The planning horizon is the run's ``planning_horizon`` metric at that
trial, else its settings', else the task's horizon. A trial's episode is the one recorded right after
its hand-over (the run's ``interaction_episodes`` metric counts those before it).
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
from harness.errors import CheckpointError, exit_on_error  # noqa: E402
from harness.task import Episode, SaturatingCost, held_cost  # noqa: E402
from plugins.mc_pilco.costs import PAPER_COSTS, StateCost  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


def planning_width(run: SavedPilcoRun) -> float:
    """The cost width the run planned with (see the module docstring for where it is read)."""
    for value in (run.params.get("learner.cost_width"), _settings(run).get("cost_width")):
        if value not in (None, "None", ""):
            return float(value)
    return float(run.task.spec.cost.width)


def _settings(run: SavedPilcoRun) -> dict:
    try:
        return run.settings
    except CheckpointError:  # an mc-pilco run has no pilco_settings.json
        return {}


def paper_cost(run: SavedPilcoRun):
    """The MC-PILCO paper's cost the run planned with (an ``mc-pilco`` run with ``cost=paper``), else ``None``."""
    return PAPER_COSTS[run.task.spec.name] if run.params.get("learner.cost") == "paper" else None


def realised_cost(cost: SaturatingCost | StateCost, episode: Episode, horizon: int) -> float:
    """The summed cost of an episode's states after the first (``states[1:horizon + 1]``), as PILCO's J
    sums the predicted states 1..H. An episode that terminated before ``horizon`` steps (a fallen unicycle)
    holds its last cost for the steps it did not take, as the harness's evaluation scores it
    (:meth:`harness.task.Episode.horizon_cost`): otherwise a policy that falls at once would look cheap."""
    return held_cost(cost(np.asarray(episode.states)[1:horizon + 1]), horizon, episode.terminated)


def check_run(run: SavedPilcoRun) -> dict:
    """One run's rows: per trial the prediction, the realised planning and task costs, the evaluation."""
    spec = run.task.spec
    width = planning_width(run)
    task_cost = spec.cost
    predicted, evaluation = run.metric("J_after"), run.metric("eval_cost")
    horizons, widths = run.metric("planning_horizon"), run.metric("cost_width")
    default_horizon = int(_settings(run).get("planning_horizon") or spec.horizon)
    episodes = run.episodes()
    before = run.metric("interaction_episodes")  # episodes recorded before each trial's hand-over
    paper, rows = paper_cost(run), []
    for trial in sorted(predicted):
        index = int(before.get(trial, len(episodes)))  # the episode the handed-over policy produced next
        if index >= len(episodes):
            continue  # the policy of the last trial was handed over but not yet applied
        horizon = int(horizons.get(trial, default_horizon))
        trial_width = widths.get(trial, width)
        planned = spec.cost.with_width(trial_width) if paper is None else paper
        rows.append({
            "trial": trial, "horizon": horizon, "width": trial_width if paper is None else None, "predicted": predicted[trial],
            "realised": realised_cost(planned, episodes[index], horizon),
            "task": realised_cost(task_cost, episodes[index], spec.horizon), "eval": evaluation.get(trial),
        })
    return {"width": width if paper is None else None, "task_width": float(task_cost.width), "rows": rows, "random": int(before.get(1, 0))}


def _planning_words(width: float | None) -> str:
    return "Planned with MC-PILCO's cost (no width)" if width is None else f"Planning width {width:g} at the start"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: print only)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    lines = ["# Predicted J against the cost really incurred, trial by trial", "",
             f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
             "Predicted: `J_after` (the model's J of the policy handed over, planning width and horizon). Realised: the "
             "same cost on the states the policy produced in its next trial. Task: the task's own cost over the task's "
             "horizon. An episode that ended early (a fall) holds its last cost for the steps it did not take, as "
             "evaluations score it. Evaluation: the run's `eval_cost` (mean over its evaluation episodes).", ""]
    for run_id in args.runs:
        with SavedPilcoRun(run_id, args.tracking_uri) as run:
            found = check_run(run)
            learner, seed, task = run.params.get("learner"), run.params.get("seed"), run.params.get("task")
        rows = found["rows"]
        gaps = [r["realised"] - r["predicted"] for r in rows]
        lines += [f"## `{run_id[:8]}`: {learner} on {task}, seed {seed}", "",
                  f"{_planning_words(found['width'])}, task width {found['task_width']:g}; {found['random']} random "
                  f"rollout(s) first. Realised minus predicted: median {np.median(gaps):+.2f}, "
                  f"largest {max(gaps, key=abs):+.2f} over {len(rows)} trials." if rows else "No applied policy.", "",
                  "| trial | H | planning width | predicted J | realised, planning cost | realised, task cost | evaluation cost |",
                  "|---|---|---|---|---|---|---|"]
        for r in rows:
            ev = "" if r["eval"] is None else f"{r['eval']:.2f}"
            lines.append(f"| {r['trial']} | {r['horizon']} | {'MC-PILCO' if r['width'] is None else format(r['width'], 'g')} | {r['predicted']:.2f} | {r['realised']:.2f} | {r['task']:.2f} | {ev} |")
        lines.append("")
        print(f"{run_id[:8]}: {len(rows)} trials, realised - predicted median "
              f"{np.median(gaps) if rows else float('nan'):+.2f}", flush=True)
    lines.append(f"Wall time {time.perf_counter() - start:.0f} s.")
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
