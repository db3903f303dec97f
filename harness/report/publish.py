"""The comparison in the MLflow UI: per task, a run ``comparison · <task>`` carrying the whole table
(``log_table``: every row, unsolved runs counted; and in its description) and the report's files of
that task, and a run per row (``harness.role = 'comparison-row'``, top level so that a search for them
lists them flat) whose metrics are the row's statistics, so that the runs table and its charts compare
the learners directly; and every reported run tagged with the row it was counted in.

The row runs are made anew by every report (a statistic that became infinite, and so is not logged,
must not leave an older value showing); the comparison run is kept and its files replaced.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from harness.configuration import bench_group_of, config_label, settings_of
from harness.report.comparison import STAT_NOTE, comparison_table
from harness.report.labels import groups
from harness.report.records import ReportData, RunRecord
from harness.store import Store, layout


#: the row runs of a task's experiment
ROWS = f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_ROW}'"


def row_metrics(row: Mapping[str, Any], runs: Sequence[RunRecord]) -> dict[str, float]:
    """A comparison row's statistics as metrics, in seconds where they are times. Infinite ones (a
    median not reached) are left out by the store; ``median_time_to_success_at_least_seconds`` is
    always finite: the median with every unsolved run counted at the interaction it used, a lower
    bound of the median (so that a learner that never solved still has a bar, at its budget)."""
    n = row["runs"]
    at_least = [r.time_to_success if r.solved and r.time_to_success is not None else r.interaction_seconds for r in runs]
    return {
        "runs": float(n),
        "solved_runs": float(row["solved"]),
        "solved_fraction": row["solved"] / n if n else math.nan,
        "stopped_runs": float(row["stopped"]),
        "failed_runs": float(row["errors"]),
        "median_time_to_success_seconds": row["median_time_to_success_s"],
        "median_ci_low_seconds": row["median_ci_low_s"],
        "median_ci_high_seconds": row["median_ci_high_s"],
        "median_time_to_success_at_least_seconds": float(np.median(at_least)) if at_least else math.nan,
        "iqm_time_to_success_seconds": row["iqm_time_to_success_s"],
        "iqm_ci_low_seconds": row["iqm_ci_low_s"],
        "iqm_ci_high_seconds": row["iqm_ci_high_s"],
        "trials_to_success_median": row["trials_to_success_median"],
        "unsolved_interaction_max_seconds": row["unsolved_interaction_max_s"],
        "wall_seconds_median": row["wall_seconds_median"],
        "median_with_stopped_low_seconds": row["median_with_stopped_low_s"],
        "median_with_stopped_high_seconds": row["median_with_stopped_high_s"],
    }


def comparison_note(task: str, rows: Sequence[Mapping[str, Any]], sweeps: Sequence[str]) -> str:
    """The comparison run's description: the table of ``comparison_<task>.md``, how to read it, where it came from."""
    return (f"**{task}: every configuration's runs, unsolved runs counted** (`report/comparison_{task}.md`)\n\n{comparison_table(rows)}\n"
            f"{STAT_NOTE}\n\nMade by `harness report` from the sweeps and bench groups {', '.join(f'`{s}`' for s in sweeps)}. "
            f"The runs tagged `{layout.ROLE_TAG} = '{layout.ROLE_ROW}'` hold each row's statistics as metrics (chart them, e.g. "
            "`solved_fraction`, `median_time_to_success_at_least_seconds`); the files are under `report/`.")


def publish_comparisons(store: Store, data: ReportData, comparisons: Mapping[str, Sequence[Mapping[str, Any]]],
                        files: Mapping[str, Sequence[Path]]) -> None:
    """Write each task's comparison (``comparisons``: its rows; ``files``: its report files) into the store."""
    sweeps = [s.sweep_id for s in data.sweeps]
    counted, stopped = groups(data.runs), groups(data.incomplete)
    for task, rows in comparisons.items():
        experiment_id = store.ensure_experiment(layout.task_experiment(task))
        found = store.search([experiment_id], f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_COMPARISON}'")
        found.sort(key=lambda r: r.start_time)
        store.delete_runs([r.run_id for r in found[1:]] + [r.run_id for r in store.search([experiment_id], ROWS)])
        if found:
            comparison = found[0].run_id
        else:
            comparison = store.create_run(experiment_id, layout.comparison_name(task),
                                          {layout.ROLE_TAG: layout.ROLE_COMPARISON, layout.TASK_TAG: task})
        store.set_tags(comparison, {layout.NOTE_TAG: comparison_note(task, rows, sweeps), "harness.sweeps": ",".join(sweeps)})
        _replace_files(store, comparison, rows, files.get(task, ()))
        for row in rows:
            label = row["learner"]
            runs, halted = counted.get(task, {}).get(label, []), stopped.get(task, {}).get(label, [])
            learner = (runs or halted)[0].learner
            run_id = store.create_run(experiment_id, layout.row_name(label, task), {
                layout.ROLE_TAG: layout.ROLE_ROW, layout.COMPARISON_TAG: comparison, layout.TASK_TAG: task,
                layout.LEARNER_TAG: learner, layout.ROW_TAG: label, "harness.sweeps": row["sweep_id"],
                layout.NOTE_TAG: f"Row `{label}` of the comparison on {task}: seeds {row['seeds'] or '–'} counted "
                                 f"({row['solved']}/{row['runs']} solved), {row['stopped']} stopped before their limit."},
                params={"learner": learner, "task": task, "row": label, "seeds": row["seeds"]})
            store.log_metrics(run_id, row_metrics(row, runs))
            store.set_status(run_id, "FINISHED")
        store.set_status(comparison, "FINISHED")
    for record in (*data.runs, *data.incomplete):
        _tag_reported(store, record)


def _replace_files(store: Store, run_id: str, rows: Sequence[Mapping[str, Any]], paths: Sequence[Path]) -> None:
    """The run's ``report/`` files: the table (``comparison.json``) and ``paths``; an older report's
    files are removed first (in a local store)."""
    root = store.run(run_id).local_root
    if root is not None:
        shutil.rmtree(root / layout.REPORT, ignore_errors=True)
    store.log_table(run_id, rows, f"{layout.REPORT}/{layout.COMPARISON_TABLE}")
    for path in paths:
        store.log_artifact(run_id, path, layout.REPORT)


def _tag_reported(store: Store, record: RunRecord) -> None:
    """The run's row in this report. A run made before the runner named and tagged runs also gets its
    configuration's hash and label, the readable name (``pilco · cartpole [horizon=30] · s3`` for
    ``pilco-cartpole-s3``) and, stopped before its limit, whether a checkpoint of it is here to resume from."""
    tags = {layout.ROW_TAG: record.label}
    run = record.reader
    if run is not None and layout.CONFIG_HASH_TAG not in run.tags:
        tags |= {layout.CONFIG_HASH_TAG: bench_group_of(run.params)[1], layout.CONFIG_LABEL_TAG: config_label(run.params)}
        if run.name == f"{record.learner}-{record.task}-s{record.seed}":
            store.rename(run.run_id, layout.run_name(record.learner, record.task, record.seed, settings_of(run.params)))
        if run.status == "KILLED" and layout.RESUMABLE_TAG not in run.tags:
            tags[layout.RESUMABLE_TAG] = str(bool(run.artifacts(layout.CHECKPOINTS))).lower()
    store.set_tags(record.run_id, tags)
