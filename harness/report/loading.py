"""Reading the store into :class:`~harness.report.records.ReportData`: the sweeps (either layout:
parents per task, or one parent in the legacy ``sweeps`` experiment) and the groups of `harness bench`
runs, the run counted for each cell, and every run or cell not counted."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from harness.configuration import bench_command, bench_group_of, option_defaults
from harness.errors import HarnessError
from harness.report.labels import label_runs
from harness.report.records import ParentRun, ReportData, RunRecord, SweepInfo, record_from_run, select_run
from harness.store import RunReader, Store, layout
from harness.sweep.spec import format_seeds


def sweep_groups(store: Store) -> list[tuple[SweepInfo, list[RunReader]]]:
    """Every sweep in the store with its child runs, in the order of their first parent; a sweep's
    oldest parent per experiment counts (one per task, or the legacy one)."""
    by_id: dict[str, dict[str, RunReader]] = {}
    for parent in store.sweep_parents():
        by_id.setdefault(parent.sweep_id, {}).setdefault(parent.experiment_id, parent)
    out = []
    for sweep_id, parents in by_id.items():
        chosen = list(parents.values())
        info = SweepInfo(sweep_id, [ParentRun(p.run_id, p.tags.get(layout.TASK_TAG, ""), p.status) for p in chosen],
                         dict(chosen[0].params))
        out.append((info, [child for p in chosen for child in store.children(p)]))
    return out


def bench_groups(store: Store) -> list[tuple[SweepInfo, list[RunReader]]]:
    """`harness bench` runs (outside sweeps), grouped by configuration into pseudo-sweeps
    ``bench-<hash>``: same learner, task, limits and resolved options; seeds vary."""
    grouped: dict[str, list[RunReader]] = defaultdict(list)
    config_of: dict[str, dict[str, str]] = {}
    for experiment_id, name in store.experiments().items():
        if name == layout.LEGACY_SWEEP_EXPERIMENT:
            continue
        for run in store.search([experiment_id]):
            if run.role or run.cell is None:
                continue
            config, group_id = bench_group_of(run.params)
            grouped[group_id].append(run)
            config_of[group_id] = config
    out = []
    for group_id, runs in grouped.items():
        c = config_of[group_id]
        seeds = format_seeds({run.cell[2] for run in runs})
        command = bench_command(c, option_defaults(c.get("learner", ""), c.get("task", "")), seeds)
        params = {"learners": c.get("learner", ""), "tasks": c.get("task", ""), "seeds": seeds, "command": command}
        out.append((SweepInfo(group_id, [], params, "bench runs"), runs))
    return out


def load(store: Store, sweep_ids: Sequence[str] | None = None, include_bench: bool = False) -> ReportData:
    """The sweeps ``sweep_ids`` (default: every sweep in the store, and with ``include_bench``
    every group of `harness bench` runs too) and their counted runs."""
    wanted = list(sweep_ids or [])
    available = sweep_groups(store)
    if include_bench or any(s.startswith("bench-") for s in wanted):
        available += bench_groups(store)
    ids = [info.sweep_id for info, _ in available]
    unknown = [s for s in wanted if s not in ids]
    if unknown:
        raise HarnessError(f"unknown sweep id {', '.join(unknown)}; sweeps in this store: {', '.join(ids) or '(none)'}")
    chosen = [(info, runs) for info, runs in available if not wanted or info.sweep_id in wanted]
    if wanted:
        chosen.sort(key=lambda g: wanted.index(g[0].sweep_id))
    if not chosen:
        hint = "" if include_bench else " (add --include-bench for `harness bench` runs)"
        raise HarnessError(f"no sweeps in the tracking store {store.uri}{hint}; run `harness sweep` first or pass --tracking-uri")

    sweeps = [info for info, _ in chosen]
    data = ReportData(sweeps, [], tracking_uri=store.uri)
    for sweep, children in chosen:
        per_cell: dict[tuple[str, str, int], list[RunRecord]] = defaultdict(list)
        for run in children:
            record = record_from_run(run, sweep.sweep_id)
            if record is not None:
                per_cell[record.cell].append(record)
        for records in per_cell.values():
            counted = select_run(records)
            (data.runs if counted.status in ("FINISHED", "FAILED") else data.incomplete).append(counted)
        data.missing += [(sweep.sweep_id, c) for c in sorted(sweep.expected_cells() - set(per_cell))]
    order = {(s.sweep_id, l): (i, j) for i, s in enumerate(sweeps) for j, l in enumerate(s.params.get("learners", "").split(","))}
    for records in (data.runs, data.incomplete):
        records.sort(key=lambda r: (order.get((r.sweep_id, r.learner), (len(sweeps), 0)), r.learner, r.task, r.seed))
    label_runs(data.runs + data.incomplete)
    return data
