"""The comparison table: a row per learner (configuration) on a task over its seeds, unsolved runs as +inf."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from harness.report.formatting import fmt_bounds, fmt_range, fmt_stat, value_range, fmt_decimal
from harness.report.records import RunRecord
from harness.statistics import bootstrap_ci, iqm, median, median_bounds, times_with_failures

#: bootstrap settings used for every CI in a report (seeded: the same store gives the same report)
BOOTSTRAP_REPS = 10_000
BOOTSTRAP_SEED = 0


def comparison_row(task: str, label: str, runs: Sequence[RunRecord], reps: int = BOOTSTRAP_REPS, seed: int = BOOTSTRAP_SEED,
                   stopped: Sequence[RunRecord] = ()) -> dict[str, Any]:
    """One learner on one task over its seeds; unsolved runs are +inf in the time statistics.

    ``stopped``: runs of the same row stopped before their limit, unsolved so far. They are in no
    statistic but one: the bounds of the median over all runs (:func:`~harness.statistics.median_bounds`,
    each stopped run needing at least the interaction it used). A row may have stopped runs only: its
    statistics over finished runs are then NaN and the bounds are all it has."""
    times = times_with_failures([r.solved for r in runs], [r.time_to_success for r in runs])
    with_stopped = median_bounds(times, [r.interaction_seconds for r in stopped])
    solved = [r for r in runs if r.solved]
    unsolved = [r for r in runs if not r.solved]
    nan2 = (math.nan, math.nan)
    med_lo, med_hi = bootstrap_ci(times, median, reps=reps, seed=seed) if runs else nan2
    iqm_lo, iqm_hi = bootstrap_ci(times, iqm, reps=reps, seed=seed) if runs else nan2
    trials = value_range([r.trials_to_success for r in solved if r.trials_to_success is not None])
    wall = value_range([r.wall_seconds for r in runs])
    return {
        "task": task,
        "learner": label,
        "sweep_id": ",".join(sorted({r.sweep_id for r in [*runs, *stopped]})),
        "runs": len(runs),
        "solved": len(solved),
        "errors": sum(r.status == "FAILED" for r in runs),
        "median_time_to_success_s": float(median(times)) if runs else math.nan,
        "median_ci_low_s": med_lo,
        "median_ci_high_s": med_hi,
        "stopped": len(stopped),
        "median_with_stopped_low_s": with_stopped[0] if stopped else math.nan,
        "median_with_stopped_high_s": with_stopped[1] if stopped else math.nan,
        "iqm_time_to_success_s": float(iqm(times)) if runs else math.nan,
        "iqm_ci_low_s": iqm_lo,
        "iqm_ci_high_s": iqm_hi,
        "trials_to_success_median": trials[0],
        "trials_to_success_min": trials[1],
        "trials_to_success_max": trials[2],
        "unsolved_interaction_min_s": min((r.interaction_seconds for r in unsolved), default=math.nan),
        "unsolved_interaction_max_s": max((r.interaction_seconds for r in unsolved), default=math.nan),
        "wall_seconds_median": wall[0],
        "wall_seconds_min": wall[1],
        "wall_seconds_max": wall[2],
        "seeds": " ".join(str(r.seed) for r in runs),
        "run_ids": " ".join(r.run_id for r in runs),
    }



STAT_NOTE = (
    "Interaction time to success in seconds of system time. Unsolved runs (limits reached, or the "
    "learner raised: 'errors') count as +∞, never dropped: a median is finite only if more than half "
    "of the runs solved, the IQM (mean of the middle 50 %) only if at most ⌊n/4⌋ runs are unsolved; "
    "'not reached' marks an infinite statistic. 95 % CIs: percentile bootstrap over seeds "
    f"({BOOTSTRAP_REPS} resamples, seed {BOOTSTRAP_SEED}, order-statistic bounds). Runs stopped before their "
    "limit (killed, or still running) are in no statistic but the last column: the lowest and highest median "
    "over all runs, a stopped run counted as solved at the interaction it had used (lowest) or never (highest); "
    "'≥ X' when the highest is ∞. Trials to success "
    "= interaction episodes, initial random ones included, over the solved runs: median [min–max]."
)


def comparison_markdown(task: str, rows: Sequence[dict[str, Any]]) -> str:
    """``comparison_<task>.md``: the task, :data:`STAT_NOTE`, then :func:`comparison_table`."""
    return "\n".join([f"## {task}", "", STAT_NOTE, "", comparison_table(rows)])


def comparison_table(rows: Sequence[dict[str, Any]]) -> str:
    """The comparison's markdown table, a line per row."""
    lines = ["| learner | solved | median time to success [95 % CI] (s) | IQM [95 % CI] (s) | trials to success | unsolved at (s) "
             "| wall time (s) | errors | median with the stopped runs (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        censored = "–" if math.isnan(r["unsolved_interaction_min_s"]) else (
            f"{r['unsolved_interaction_min_s']:.1f}" if r["unsolved_interaction_min_s"] == r["unsolved_interaction_max_s"]
            else f"{r['unsolved_interaction_min_s']:.1f}–{r['unsolved_interaction_max_s']:.1f}")
        lines.append(
            f"| {r['learner']} | {r['solved']}/{r['runs']} "
            f"| {fmt_stat(r['median_time_to_success_s'], r['median_ci_low_s'], r['median_ci_high_s'])} "
            f"| {fmt_stat(r['iqm_time_to_success_s'], r['iqm_ci_low_s'], r['iqm_ci_high_s'])} "
            f"| {fmt_range(r['trials_to_success_median'], r['trials_to_success_min'], r['trials_to_success_max'])} "
            f"| {censored} | {fmt_range(r['wall_seconds_median'], r['wall_seconds_min'], r['wall_seconds_max'], fmt=fmt_decimal)} | {r['errors']} "
            f"| {fmt_bounds(r['median_with_stopped_low_s'], r['median_with_stopped_high_s'], r['stopped'], r['runs'])} |"
        )
    return "\n".join(lines) + "\n"
