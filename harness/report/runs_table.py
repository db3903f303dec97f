"""The table of every run of a task: counted runs, then the runs stopped before their limit."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from harness.report.formatting import fmt_number
from harness.report.records import RunRecord


RUNS_FIELDS = ["task", "learner", "seed", "counted", "solved", "time_to_success_s", "trials_to_success", "interaction_used_s",
               "episodes", "wall_seconds", "stop_reason", "status", "run_id"]


def run_rows(task: str, label: str, runs: Sequence[RunRecord], counted: bool = True) -> list[dict[str, Any]]:
    """One row per run; an unsolved run has no time to success (``nan``), only the interaction it
    used before it stopped. ``counted=False``: runs stopped before their limit (KILLED, or RUNNING
    at the time of the report), listed with the interaction and trials they reached but in no
    statistic; their label gets :data:`~harness.report.figures.STOPPED_SUFFIX`."""
    from harness.report.figures import STOPPED_SUFFIX

    return [{
        "task": task, "learner": label if counted else label + STOPPED_SUFFIX, "seed": r.seed, "counted": counted,
        "solved": r.solved,
        "time_to_success_s": r.time_to_success if r.solved and r.time_to_success is not None else math.nan,
        "trials_to_success": r.trials_to_success if r.solved and r.trials_to_success is not None else math.nan,
        "interaction_used_s": r.interaction_seconds, "episodes": r.episodes if r.episodes is not None else math.nan,
        "wall_seconds": r.wall_seconds,
        "stop_reason": r.stop_reason if counted else f"stopped before its limit ({r.status})", "status": r.status, "run_id": r.run_id,
    } for r in runs]


def runs_markdown(task: str, rows: Sequence[dict[str, Any]]) -> str:
    lines = [f"## {task}: every run", "",
             "Time to success = interaction seconds before the first solved evaluation; an unsolved run shows "
             "'> X' with X the interaction it used before it stopped (a lower bound, not a value). "
             "Trials = interaction episodes, initial random ones included. Wall = the run's own wall-clock time. "
             "Rows marked *stopped* are runs stopped before their limit (killed, or still running): they are "
             "in no statistic (but the bounds of the median in comparison_<task>.md) and their '> X' is only how far they got.", "",
             "| learner | seed | solved | time to success (s) | trials | interaction used (s) | wall (s) | stop | run |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("counted", True):
            time = f"{r['time_to_success_s']:.1f}" if r["solved"] else f"> {r['interaction_used_s']:.1f} (unsolved)"
            trials = fmt_number(r["trials_to_success"]) if r["solved"] else "–"
        else:
            time = f"> {r['interaction_used_s']:.1f} (*stopped*, unsolved so far)"
            trials = f"– ({fmt_number(r['episodes'])} so far)"
        lines.append(f"| {r['learner']} | {r['seed']} | {'yes' if r['solved'] else 'no'} | {time} | {trials} "
                     f"| {r['interaction_used_s']:.1f} | {r['wall_seconds']:.0f} | {r['stop_reason']} | `{r['run_id'][:8]}` |")
    return "\n".join(lines) + "\n"
