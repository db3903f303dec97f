"""Where the wall time goes: per trial, split into the parts the learners declare they time
(:attr:`harness.learner_logs.Logs.timings`), the evaluation and the rest."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from harness.learner_logs import EVALUATION, Timing, declared_logs
from harness.report.formatting import fmt_range, fmt_number, value_range
from harness.store import layout


def wall_parts(learners: Iterable[str]) -> tuple[Timing, ...]:
    """The timed parts of the learners' trials (each learner's declared timings, first seen first,
    a metric once), then the harness's evaluation: the columns of a task's wall-time table."""
    parts = {t.metric: t for learner in dict.fromkeys(learners) for t in declared_logs(learner).timings}
    return (*(t for t in parts.values() if t.metric != EVALUATION.metric), EVALUATION)


def wall_breakdown(series: Sequence[dict[str, dict[int, float]]], parts: Sequence[Timing] = (EVALUATION,)) -> dict[str, Any]:
    """Where the wall time of some runs went, per trial.

    ``series``: per run, ``metric -> {step: value}`` for ``wall_seconds`` (cumulative) and the
    ``parts``' metrics. A trial's wall time is the increase of ``wall_seconds`` over the previous
    trial (the first trial's includes the set-up and initial rollouts). Returns the number of
    trials (``policies``: policies handed over), the median and range of the per-trial wall time,
    the median wall time of the runs' last trial, the total, and each part's share of the total
    (``share_<key>``, ``nan`` where no run logs it; ``share_other`` = the rest: rollouts, logging, checkpoints)."""
    walls, last, total, spent = [], [], 0.0, {part.key: 0.0 for part in parts}
    logged = {part.key: False for part in parts}
    for metrics in series:
        cumulative = metrics.get(layout.WALL_SECONDS, {})
        steps = sorted(cumulative)
        per_trial = np.diff([0.0] + [cumulative[s] for s in steps])
        if per_trial.size:
            walls += per_trial.tolist()
            last.append(float(per_trial[-1]))
            total += float(per_trial.sum())
        for part in parts:
            values = [metrics.get(part.metric, {}).get(s) for s in steps]
            values = [v for v in values if v is not None and math.isfinite(v)]
            if values:
                logged[part.key] = True
                spent[part.key] += float(sum(values))
    wall = value_range(walls)
    row: dict[str, Any] = {"policies": len(walls), "wall_per_trial_median_s": wall[0], "wall_per_trial_min_s": wall[1],
                           "wall_per_trial_max_s": wall[2], "last_trial_wall_median_s": value_range(last)[0], "total_wall_s": total}
    for part in parts:
        row[f"share_{part.key}"] = spent[part.key] / total if logged[part.key] and total > 0 else math.nan
    row["share_other"] = (total - sum(spent.values())) / total if total > 0 else math.nan
    return row


def walltime_markdown(task: str, rows: Sequence[dict[str, Any]], parts: Sequence[Timing] = (EVALUATION,)) -> str:
    pct = lambda v: "–" if math.isnan(v) else f"{100 * v:.0f} %"  # noqa: E731
    lines = [f"## {task}: where the wall time goes", "",
             "Per trial = one policy handed over: the learner's work for it (PILCO: GP training, policy search), the harness's "
             "evaluation episodes, the trial's rollout and the logging. Wall per trial grows with the data, so the "
             "last trial's is given too. Shares are of the total wall time of all trials of the row's runs; '–' = not "
             "logged by that learner (or by runs made before `eval_seconds` was logged, whose evaluation is then in "
             "'other'). Machine: shared, 2 cores, one torch thread per run; wall times are upper bounds.", "",
             "| learner | runs | policies | wall per trial, median [range] (s) | last trial (s, median) | total (h) "
             + "".join(f"| {part.title} " for part in parts) + "| other |",
             "|" + "---|" * (7 + len(parts))]
    for r in rows:
        lines.append(f"| {r['learner']} | {r['runs']} | {r['policies']} | {fmt_range(r['wall_per_trial_median_s'], r['wall_per_trial_min_s'], r['wall_per_trial_max_s'])} "
                     f"| {fmt_number(r['last_trial_wall_median_s'])} | {r['total_wall_s'] / 3600:.2f} "
                     + "".join(f"| {pct(r[f'share_{part.key}'])} " for part in parts) + f"| {pct(r['share_other'])} |")
    return "\n".join(lines) + "\n"
