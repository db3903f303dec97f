"""``harness report``: every table and figure from the store, written into a folder, and (for named
sweeps) the comparison published in the store itself (:mod:`harness.report.publish`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from harness.report import figures
from harness.report.fig5 import FIG5_FIELDS, FIG5_TASKS, fig5_data, plot_fig5
from harness.report.comparison import comparison_markdown, comparison_row
from harness.report.formatting import write_csv
from harness.report.from_runs import copy_test_histogram, copy_trial_figure, test_markdown, test_rows
from harness.report.labels import groups
from harness.report.loading import load
from harness.report.notes import notes_markdown
from harness.report.paper import TABLE1_FIELDS, flat_table1, read_literature, table1_markdown, table1_rows
from harness.report.records import RunRecord
from harness.report.runs_table import RUNS_FIELDS, run_rows, runs_markdown
from harness.report.walltime import wall_breakdown, wall_parts, walltime_markdown
from harness.store import Store, layout


def history(run: RunRecord) -> dict[str, np.ndarray]:
    """Per hand-over: ``interaction_seconds``, ``eval_success_rate``, ``eval_cost`` aligned on the step."""
    keys = (layout.INTERACTION_SECONDS, layout.EVAL_SUCCESS_RATE, layout.EVAL_COST)
    series = {key: run.reader.history(key) for key in keys}
    steps = sorted(set.intersection(*(set(s) for s in series.values())))
    return {key: np.array([series[key][s] for s in steps], dtype=np.float64) for key in keys}


def make_report(
    store: Store,
    out: Path,
    sweep_ids: Sequence[str] | None = None,
    table1_learner: str = "pilco",
    fig5_tasks: Sequence[str] = FIG5_TASKS,
    literature: Path | None = None,
    include_bench: bool = False,
    publish: bool | None = None,
) -> list[Path]:
    """Write every table and figure into ``out`` and return the written paths. ``publish`` (default:
    when ``sweep_ids`` are given) also writes each task's comparison into the store
    (:func:`~harness.report.publish.publish_comparisons`)."""
    data = load(store, sweep_ids, include_bench)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    by_task = groups(data.runs)
    stopped_by_task = groups(data.incomplete)
    tasks = list(dict.fromkeys([*by_task, *stopped_by_task]))
    of_task: dict[str, list[Path]] = {task: [] for task in tasks}
    comparisons: dict[str, list[dict[str, Any]]] = {}

    def wrote(task: str | None, *paths: Path) -> None:
        written.extend(paths)
        if task is not None:
            of_task[task].extend(paths)

    for task in tasks:
        by_label, stopped = by_task.get(task, {}), stopped_by_task.get(task, {})
        labels = dict.fromkeys([*by_label, *stopped])  # a configuration whose runs are all stopped has a row too
        comparisons[task] = [comparison_row(task, label, by_label.get(label, []), stopped=stopped.get(label, ())) for label in labels]
        md = out / f"comparison_{task}.md"
        md.write_text(comparison_markdown(task, comparisons[task]))
        wrote(task, md, write_csv(out / f"comparison_{task}.csv", comparisons[task]))

    for task in tasks:
        rows = [row for label, runs in by_task.get(task, {}).items() for row in run_rows(task, label, runs)]
        rows += [row for label, runs in stopped_by_task.get(task, {}).items() for row in run_rows(task, label, runs, counted=False)]
        (out / f"runs_{task}.md").write_text(runs_markdown(task, rows))
        wrote(task, out / f"runs_{task}.md", write_csv(out / f"runs_{task}.csv", rows, RUNS_FIELDS))

    # figures and tests of saved policies: runs stopped before their limit have real policies too
    for task, by_label in groups([*data.runs, *data.incomplete]).items():
        tested: list[dict[str, Any]] = []
        for label, runs in by_label.items():
            figure = copy_trial_figure(task, label, runs, out)
            label_tested = test_rows(task, label, runs)
            tested += label_tested
            histogram = copy_test_histogram(task, label, runs, label_tested, out)
            wrote(task, *(path for path in (figure, histogram) if path is not None))
        if tested:
            (out / f"test_{task}.md").write_text(test_markdown(task, tested))
            wrote(task, out / f"test_{task}.md", write_csv(out / f"test_{task}.csv", tested))

    t1 = table1_rows(by_task, table1_learner, data.incomplete)
    (out / "table1.md").write_text(table1_markdown(t1, table1_learner))
    wrote(None, out / "table1.md", write_csv(out / "table1.csv", flat_table1(t1), TABLE1_FIELDS))

    lit = read_literature(literature if literature is not None else out / "literature_fig5.csv")
    fig5_rows = fig5_data(by_task, lit, fig5_tasks)
    fig5_files = (write_csv(out / "fig5.csv", fig5_rows, FIG5_FIELDS), plot_fig5(fig5_rows, out / "fig5.png", fig5_tasks))
    wrote(None, *fig5_files)
    for task in dict.fromkeys(fig5_tasks):
        of_task.get(task, []).extend(fig5_files)  # published with each task's comparison

    for task in tasks:
        curves = {label: [history(r) for r in runs] for label, runs in by_task.get(task, {}).items()}
        stopped = {label + figures.STOPPED_SUFFIX: [history(r) for r in runs] for label, runs in stopped_by_task.get(task, {}).items()}
        curves.update(stopped)
        table = figures.curve_table(curves, stopped=frozenset(stopped))
        wrote(task, write_csv(out / f"curves_{task}.csv", table), figures.plot_curves(table, out / f"curves_{task}.png", task, curves))

    for task in tasks:
        rows = []
        parts = wall_parts(r.learner for runs in (*by_task.get(task, {}).values(), *stopped_by_task.get(task, {}).values()) for r in runs)
        for runs_of, suffix in ((by_task.get(task, {}), ""), (stopped_by_task.get(task, {}), figures.STOPPED_SUFFIX)):
            for label, runs in runs_of.items():
                series = [{key: r.reader.history(key) for key in (layout.WALL_SECONDS, *(p.metric for p in parts))} for r in runs]
                rows.append({"task": task, "learner": label + suffix, "runs": len(runs), **wall_breakdown(series, parts)})
        (out / f"walltime_{task}.md").write_text(walltime_markdown(task, rows, parts))
        wrote(task, out / f"walltime_{task}.md", write_csv(out / f"walltime_{task}.csv", rows))

    (out / "sweeps.md").write_text(notes_markdown(data))
    wrote(None, out / "sweeps.md")

    if publish if publish is not None else bool(sweep_ids):
        from harness.report.publish import publish_comparisons

        publish_comparisons(store, data, comparisons, of_task)
    return written
