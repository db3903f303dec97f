"""What the report copies from runs' files: a representative run's last per-trial figure (the one its
learner declares, :attr:`harness.learner_logs.Logs.trial_figure`: PILCO's prediction plot), and the
results of ``harness eval`` (``test_*`` metrics, the final-distance histogram)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from harness.errors import MissingArtifactsWarning
from harness.learner_logs import declared_logs
from harness.report.labels import file_slug
from harness.report.records import RunRecord
from harness.statistics import rate_interval
from harness.store import layout


def representative_run(runs: Sequence[RunRecord]) -> RunRecord | None:
    """The solved run with the median time to success (lower median), else the longest run."""
    solved = sorted((r for r in runs if r.solved and r.time_to_success is not None), key=lambda r: (r.time_to_success, r.seed))
    if solved:
        return solved[(len(solved) - 1) // 2]
    return max(runs, key=lambda r: (r.interaction_seconds, -r.seed), default=None)


def _has_files(run: RunRecord, what: str, task: str, label: str, role: str) -> bool:
    """Whether the run has any files here; if not (its artifact folder was not copied with the
    database), a :class:`MissingArtifactsWarning` says that ``what`` was not written."""
    if run.reader is not None and run.reader.artifacts():
        return True
    warnings.warn(f"{what} of {task} / {label} not written: its {role} run {run.run_id} has no artifacts in the store "
                  "(was its artifact folder copied with the database?)", MissingArtifactsWarning, stacklevel=3)
    return False


def copy_trial_figure(task: str, label: str, runs: Sequence[RunRecord], out: Path) -> Path | None:
    """The representative run's last per-trial figure, as ``<figure name>_<task>_<label>.png``
    (``None`` if its learner declares none or the run has none)."""
    run = representative_run(runs)
    figure = declared_logs(run.learner).trial_figure if run is not None else None
    if run is None or figure is None or not _has_files(run, f"{figure.name} figure", task, label, "representative"):
        return None
    found = run.reader.trial_files(figure.pattern)
    if not found:
        return None
    return run.reader.copy(found[-1], out / f"{figure.name}_{task}_{file_slug(label)}{Path(found[-1]).suffix}")


def test_rows(task: str, label: str, runs: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """One row per run whose saved policy was tested with ``harness eval`` (its ``test_*`` metrics)."""
    rows = []
    for r in sorted(runs, key=lambda r: r.seed):
        metrics = r.reader.metrics if r.reader is not None else {}
        if layout.TEST_SUCCESS_RATE in metrics:
            rows.append({"task": task, "learner": label, "seed": r.seed, "solved": r.solved,
                         "finished": r.status in ("FINISHED", "FAILED"),
                         "test_episodes": int(metrics.get(layout.TEST_EPISODES, 0)),
                         "test_success_rate": metrics[layout.TEST_SUCCESS_RATE], "run_id": r.run_id})
    return rows


def test_markdown(task: str, rows: Sequence[dict[str, Any]]) -> str:
    lines = [f"# `{task}`: saved policies tested on fresh episodes (`harness eval RUN_ID --episodes N`)", "",
             "Test episodes start from the task's initial distribution on a new environment (seed 12345 + i); they are "
             "not interaction. Success: the task's own rule. The histogram of final distances from the goal of the "
             f"representative tested run is `fig4b_{task}_<learner>.png` (the paper's Fig. 4b for the unicycle).", "",
             "| learner | seed | solved in training | test episodes | test success rate [95 % interval] | run |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        training = "yes" if r["solved"] else ("no" if r["finished"] else "no (run stopped before its limit)")
        n = r["test_episodes"]
        interval = ""
        if n >= 1:  # Wilson score interval of the rate over the test episodes
            low, high = rate_interval(r["test_success_rate"], n)
            interval = f" [{100 * low:.1f}, {100 * high:.1f}]"
        lines.append(f"| {r['learner']} | {r['seed']} | {training} | {n} "
                     f"| {100 * r['test_success_rate']:.1f} %{interval} | `{r['run_id'][:8]}` |")
    return "\n".join(lines) + "\n"


def copy_test_histogram(task: str, label: str, runs: Sequence[RunRecord], tested: Sequence[dict[str, Any]],
                        out: Path) -> Path | None:
    """The final-distance histogram of the representative run if it was tested, else of the first tested run."""
    ids = [row["run_id"] for row in tested]
    if not ids:
        return None
    rep = representative_run(runs)
    run = rep if rep is not None and rep.run_id in ids else next(r for r in runs if r.run_id == ids[0])
    if not _has_files(run, "test histogram", task, label, "tested"):
        return None
    names = [a.path for a in run.reader.artifacts(layout.TEST) if a.name == layout.TEST_HISTOGRAM]
    if not names:
        return None
    return run.reader.copy(names[0], out / f"fig4b_{task}_{file_slug(label)}.png")
