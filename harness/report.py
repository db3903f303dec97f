"""``harness report``: tables and figures from the MLflow store alone (nothing is re-run).

Reads the sweeps' child runs (see :mod:`harness.sweep` for the layout) and writes into ``out``:

* ``comparison_<task>.md`` / ``.csv``: learner x {solved seeds, median and IQM of interaction
  time to success with 95 % stratified-bootstrap CIs, trials to success, wall time, and the bounds
  of the median with the row's stopped runs};
* ``table1.md`` / ``.csv``: the paper's Table 1 (state dimension, trials, experience, policy
  parameters) measured, median [range], beside the paper's values;
* ``fig5.png`` / ``fig5.csv``: interaction time to learn cart-pole, log axis, one bar per learner
  (and literature rows from ``literature_fig5.csv``, each with its source);
* ``runs_<task>.md`` / ``.csv``: one row per counted run (seed, solved, time to success or the
  interaction at which it stopped unsolved, trials, wall time, stop reason, run id), then the
  runs stopped before their limit, marked as such (in no statistic but the median's bounds);
* ``curves_<task>.png`` / ``.csv``: evaluation success rate and cost vs interaction seconds
  (mean with band, and every run as a thin line); runs stopped before their limit get a row
  ``<label> (stopped)`` of their own, dashed, ending where they stopped;
* ``prediction_<task>_<row>.png``: for learners that log predicted-vs-realised cost plots
  (PILCO's ``prediction_trial*.png``), the last one of a representative run: the solved run with
  the median time to success (lower median), else the run with the most hand-overs;
* ``walltime_<task>.md`` / ``.csv``: where the wall time goes, per row: wall per trial (median,
  range, last trial) and the shares of GP training, policy search, evaluation and the rest;
* ``sweeps.md``: which sweeps (ids, commands, store) the files were made from.

Rows are named by learner. Where a learner ran on a task in several sweeps, each sweep's row is
named by the settings its runs differ in (``pilco [horizon=30]`` beside ``pilco [horizon=40]``),
with ``@<sweep id>`` added where settings do not tell sweeps apart; files named after a row use
the same name as a slug (``prediction_cartpole_pilco_horizon-30.png``).

With ``include_bench``, `harness bench` runs outside sweeps are reported too, grouped by
configuration (learner, task, limits, resolved options) into pseudo-sweeps ``bench-<hash>``
(options at their current default are left out of the hash: an option added later does not split
a group).

Which run counts for a cell: the newest FINISHED child of the cell, else the newest child. A cell
whose counted run FAILED (the learner raised) counts as unsolved and is listed under "errors";
a cell still RUNNING or KILLED is not counted and is listed as incomplete (a RUNNING run whose
process, tag ``harness.process``, is gone from this machine is said to be stale); a cell of the sweep's
spec without any run is listed as missing. Nothing is dropped without being named.

When sweep ids are given, each sweep's rows are also logged on its parent run with
``log_table`` (``report/comparison.json``), beside the markdown tables.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import json
import math
import re
import warnings
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import HarnessError, MissingArtifactsWarning
from harness.provenance import PROCESS_TAG, process_alive
from harness.statistics import bootstrap_ci, iqm, median, median_bounds, times_with_failures
from harness.sweep import ERROR_TAG, ROLE_TAG, SWEEP_EXPERIMENT, SWEEP_TAG, _search_all, format_seeds, parse_seeds

#: bootstrap settings used for every CI in a report (seeded: the same store gives the same report)
BOOTSTRAP_REPS = 10_000
BOOTSTRAP_SEED = 0

#: ICML 2011 Table 1, per harness task name: (paper task name, state space, # trials, experience, parameters)
PAPER_TABLE1: dict[str, tuple[str, str, str, str, str]] = {
    "cartpole": ("cart-pole", "R^4", "<= 10", "~ 20 s", "R^305"),
    "double-pendulum": ("cart-double-pole", "R^6", "20-30", "~ 60-90 s", "R^1816"),
    "unicycle": ("unicycle", "R^12", "~ 20", "~ 20-30 s", "R^28"),
}


@dataclass
class SweepInfo:
    """A sweep's parent run."""

    sweep_id: str
    parent_run_id: str
    params: dict[str, str]
    status: str

    def expected_cells(self) -> set[tuple[str, str, int]]:
        try:
            learners = [s for s in self.params["learners"].split(",") if s]
            tasks = [s for s in self.params["tasks"].split(",") if s]
            seeds = parse_seeds(self.params["seeds"])
        except (KeyError, HarnessError):
            return set()
        return {(l, t, s) for l in learners for t in tasks for s in seeds}


@dataclass
class RunRecord:
    """One child run as the report needs it (from its tags, params and final metrics)."""

    run_id: str
    sweep_id: str
    learner: str
    task: str
    seed: int
    status: str
    start_time: int
    solved: bool
    stop_reason: str
    time_to_success: float | None
    trials_to_success: float | None
    interaction_seconds: float
    wall_seconds: float
    policy_parameters: float | None
    state_dim: int | None
    error: str = ""
    label: str = ""
    #: interaction episodes the run recorded, random ones included (like ``interaction_seconds``:
    #: a stopped run's count includes the rollout of its last policy)
    episodes: float | None = None
    #: what the run was configured with: limits and resolved options (params ``learner.*``, ``task.*``)
    config: dict[str, str] = field(default_factory=dict)
    #: the process that last logged into the run (tag :data:`harness.provenance.PROCESS_TAG`)
    process: str = ""

    @property
    def cell(self) -> tuple[str, str, int]:
        return (self.learner, self.task, self.seed)


def _metric(metrics: dict[str, float], key: str) -> float | None:
    value = metrics.get(key)
    return None if value is None or not math.isfinite(value) else float(value)


#: run params that say how a run was configured besides learner, task and seed
_LIMIT_KEYS = ("max_trials", "budget_seconds", "eval_episodes")


def run_config(params: dict[str, str]) -> dict[str, str]:
    """The limits and resolved options among a run's params, without the execution options
    (threads, kernel: :attr:`harness.options.Option.execution`) of the installed plugins."""
    skip = _execution_keys(params.get("learner", ""), params.get("task", ""))
    return {k: v for k, v in params.items() if (k in _LIMIT_KEYS or k.startswith(("learner.", "task."))) and k not in skip}


@functools.lru_cache(maxsize=None)
def _execution_keys(learner: str, task: str) -> frozenset[str]:
    """``learner.<k>``/``task.<k>`` of the execution options of the installed plugins (none for one
    that is not installed here)."""
    from harness.discovery import load_learner, load_task

    keys: set[str] = set()
    for prefix, loader, name in (("learner", load_learner, learner), ("task", load_task, task)):
        try:
            keys |= {f"{prefix}.{k}" for k in loader(name).option_set().execution_names()}
        except HarnessError:
            continue
    return frozenset(keys)


def _latest_total(metrics: dict[str, float], key: str) -> float:
    """How far a run got in ``key`` (a cumulative count): its ``<key>_total``, logged when a run
    segment ends, or its last per-trial ``<key>``, whichever is larger. A run resumed after a kill
    that logged no totals (SIGKILL, a machine's end) has a stale total from an earlier segment."""
    return max(_metric(metrics, f"{key}_total") or 0.0, _metric(metrics, key) or 0.0)


def record_from_run(run, sweep_id: str) -> RunRecord | None:
    """A :class:`RunRecord` from an MLflow ``Run`` (``None`` if it is not a sweep cell)."""
    tags, metrics, params = run.data.tags, run.data.metrics, run.data.params
    try:
        learner, task, seed = tags["learner"], tags["task"], int(tags["seed"])
    except (KeyError, ValueError):
        return None
    solved = tags.get("solved") == "true" and run.info.status == "FINISHED"
    state_dim = params.get("spec.state_dim")
    return RunRecord(
        run_id=run.info.run_id, sweep_id=sweep_id, learner=learner, task=task, seed=seed,
        status=run.info.status, start_time=int(run.info.start_time or 0), solved=solved,
        stop_reason=tags.get("stop_reason", run.info.status.lower()),
        time_to_success=_metric(metrics, "interaction_time_to_success") if solved else None,
        trials_to_success=_metric(metrics, "trials_to_success") if solved else None,
        interaction_seconds=_latest_total(metrics, "interaction_seconds"),
        wall_seconds=_latest_total(metrics, "wall_seconds"),
        policy_parameters=_metric(metrics, "policy_parameters"),
        state_dim=int(float(state_dim)) if state_dim not in (None, "") else None,
        error=tags.get(ERROR_TAG, ""),
        episodes=_latest_total(metrics, "interaction_episodes"),
        config=run_config(params),
        process=tags.get(PROCESS_TAG, ""),
    )


# ---------------------------------------------------------------------------------------------
# reading the store
# ---------------------------------------------------------------------------------------------


@dataclass
class ReportData:
    """The counted runs, and every run that was not counted, with why."""

    sweeps: list[SweepInfo]
    runs: list[RunRecord]
    incomplete: list[RunRecord] = field(default_factory=list)
    missing: list[tuple[str, tuple[str, str, int]]] = field(default_factory=list)
    tracking_uri: str = ""


def _sweep_groups(client) -> list[tuple[SweepInfo, list]]:
    """Every sweep in the store (oldest parent per id) with its child runs."""
    experiment = client.get_experiment_by_name(SWEEP_EXPERIMENT)
    if experiment is None:
        return []
    parents = _search_all(client, experiment.experiment_id, f"tags.`{ROLE_TAG}` = 'sweep'")
    by_id: dict[str, Any] = {}
    for run in sorted(parents, key=lambda r: r.info.start_time):
        by_id.setdefault(run.data.tags[SWEEP_TAG], run)
    out = []
    for sweep_id, parent in by_id.items():
        info = SweepInfo(sweep_id, parent.info.run_id, dict(parent.data.params), parent.info.status)
        out.append((info, _search_all(client, experiment.experiment_id, f"tags.`mlflow.parentRunId` = '{parent.info.run_id}'")))
    return out


def bench_group_id(config: dict[str, str], defaults: dict[str, str]) -> str:
    """``bench-<hash>`` of a run's configuration without the options at their current default
    (``defaults``, params as strings): a run made before an option existed and one made after,
    with the option at its default, did the same and share a group."""
    blob = json.dumps(sorted((k, v) for k, v in config.items() if defaults.get(k) != v))
    return "bench-" + hashlib.sha256(blob.encode()).hexdigest()[:8]


def bench_group_of(params: dict[str, str]) -> tuple[dict[str, str], str]:
    """A `harness bench` run's configuration (learner, task, limits, resolved options) from its
    logged params, and the ``bench-<hash>`` group that `harness report --sweep` knows it by."""
    config = {k: v for k, v in params.items() if k in ("learner", "task")} | run_config(params)
    return config, bench_group_id(config, _option_defaults(config.get("learner", ""), config.get("task", "")))


@functools.lru_cache(maxsize=None)
def _option_defaults(learner: str, task: str) -> dict[str, str]:
    """The installed plugins' option defaults as logged params (``learner.<k>``, ``task.<k>``);
    empty for a plugin that is not installed here."""
    from harness.discovery import load_learner, load_task

    defaults: dict[str, str] = {}
    for prefix, loader, name in (("learner", load_learner, learner), ("task", load_task, task)):
        try:
            option_set = loader(name).option_set()
        except HarnessError:
            continue
        defaults.update({f"{prefix}.{k}": str(v) for k, v in option_set.defaults().items()})
    return defaults


def bench_command(config: dict[str, str], defaults: dict[str, str], seeds: str) -> str:
    """The `harness bench` command behind a bench group: its limits and one ``--set`` per option
    that differs from the installed default (``defaults``, params as strings; an option of a
    plugin not installed here is written out whatever its value), for the seeds ``seeds``."""
    limits = "".join(f" --{k.replace('_', '-')} {config[k]}" for k in ("max_trials", "budget_seconds")
                     if config.get(k) not in (None, "None"))
    sets = "".join(f" --set {k}={v}" for k, v in sorted(config.items())
                   if k.startswith(("learner.", "task.")) and defaults.get(k) != v)
    return (f"harness bench --learner {config.get('learner')} --task {config.get('task')} --seed S{limits}"
            f" --eval-episodes {config.get('eval_episodes')}{sets}  (S = {seeds})")


def _bench_groups(client) -> list[tuple[SweepInfo, list]]:
    """`harness bench` runs (outside sweeps), grouped by configuration into pseudo-sweeps
    ``bench-<hash>``: same learner, task, limits and resolved options; seeds vary."""
    grouped: dict[str, list] = defaultdict(list)
    config_of: dict[str, dict[str, str]] = {}
    for experiment in client.search_experiments():
        if experiment.name == SWEEP_EXPERIMENT:
            continue
        for run in _search_all(client, experiment.experiment_id, ""):
            if ROLE_TAG in run.data.tags or "learner" not in run.data.tags:
                continue
            config, group_id = bench_group_of(run.data.params)
            grouped[group_id].append(run)
            config_of[group_id] = config
    out = []
    for group_id, runs in grouped.items():
        c = config_of[group_id]
        seeds = sorted({int(r.data.tags["seed"]) for r in runs if r.data.tags.get("seed", "").isdigit()})
        command = bench_command(c, _option_defaults(c.get("learner", ""), c.get("task", "")), format_seeds(seeds))
        params = {"learners": c.get("learner", ""), "tasks": c.get("task", ""), "seeds": format_seeds(seeds), "command": command}
        out.append((SweepInfo(group_id, "", params, "bench runs"), runs))
    return out


def load(client, sweep_ids: Sequence[str] | None = None, tracking_uri: str = "", include_bench: bool = False) -> ReportData:
    """The sweeps ``sweep_ids`` (default: every sweep in the store, and with ``include_bench``
    every group of `harness bench` runs too) and their counted runs."""
    wanted = list(sweep_ids or [])
    available = _sweep_groups(client)
    if include_bench or any(s.startswith("bench-") for s in wanted):
        available += _bench_groups(client)
    ids = [info.sweep_id for info, _ in available]
    unknown = [s for s in wanted if s not in ids]
    if unknown:
        raise HarnessError(f"unknown sweep id {', '.join(unknown)}; sweeps in this store: {', '.join(ids) or '(none)'}")
    chosen = [(info, runs) for info, runs in available if not wanted or info.sweep_id in wanted]
    if wanted:
        chosen.sort(key=lambda g: wanted.index(g[0].sweep_id))
    if not chosen:
        hint = "" if include_bench else " (add --include-bench for `harness bench` runs)"
        raise HarnessError(f"no sweeps in the tracking store {tracking_uri or '(default)'}{hint}; run `harness sweep` first or pass --tracking-uri")

    sweeps = [info for info, _ in chosen]
    data = ReportData(sweeps, [], tracking_uri=tracking_uri)
    for sweep, children in chosen:
        per_cell: dict[tuple[str, str, int], list[RunRecord]] = defaultdict(list)
        for run in children:
            record = record_from_run(run, sweep.sweep_id)
            if record is not None:
                per_cell[record.cell].append(record)
        for cell, records in per_cell.items():
            chosen_run = select_run(records)
            (data.runs if chosen_run.status in ("FINISHED", "FAILED") else data.incomplete).append(chosen_run)
        data.missing += [(sweep.sweep_id, c) for c in sorted(sweep.expected_cells() - set(per_cell))]
    order = {(s.sweep_id, l): (i, j) for i, s in enumerate(sweeps) for j, l in enumerate(s.params.get("learners", "").split(","))}
    for records in (data.runs, data.incomplete):
        records.sort(key=lambda r: (order.get((r.sweep_id, r.learner), (len(sweeps), 0)), r.learner, r.task, r.seed))
    _label(data.runs + data.incomplete)
    return data


def select_run(records: Sequence[RunRecord]) -> RunRecord:
    """The newest FINISHED run of a cell, else the newest run."""
    finished = [r for r in records if r.status == "FINISHED"]
    return max(finished or records, key=lambda r: r.start_time)


#: at most this many differing settings in a row label; more, and the label is ``learner@<sweep id>``
LABEL_SETTINGS = 5


def _label(records: Sequence[RunRecord]) -> None:
    """Row label = learner. Where a learner-task pair is in several sweeps, each sweep's row is the
    learner with the settings its runs differ in, e.g. ``pilco [horizon=30]`` beside
    ``pilco [horizon=40]``, with ``@<sweep id>`` added where settings do not tell sweeps apart. A
    setting a sweep did not record (an option added after it ran) counts at the installed default."""
    by_pair: dict[tuple[str, str], dict[str, list[RunRecord]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        by_pair[(r.learner, r.task)][r.sweep_id].append(r)
    for (learner, task), by_sweep in by_pair.items():
        if len(by_sweep) == 1:
            names = dict.fromkeys(by_sweep, learner)
        else:
            defaults = _option_defaults(learner, task)
            configs = {sweep: {**defaults, **_shared_config(rs)} for sweep, rs in by_sweep.items()}
            names = variant_labels(learner, configs)
        for sweep, rs in by_sweep.items():
            for r in rs:
                r.label = names[sweep]


def _shared_config(records: Sequence[RunRecord]) -> dict[str, str]:
    """The settings every one of ``records`` was run with."""
    shared = dict(records[0].config)
    for r in records[1:]:
        shared = {k: v for k, v in shared.items() if r.config.get(k) == v}
    return shared


def variant_labels(learner: str, configs: dict[str, dict[str, str]]) -> dict[str, str]:
    """``sweep id -> label`` for several sweeps of one learner on one task, from each sweep's shared
    settings (``configs``): the settings recorded in every sweep whose values differ, by their option
    name (``task.horizon`` -> ``horizon``). Settings missing from a sweep (an option added after it
    ran) are not compared. Sweeps whose settings do not tell them apart get ``@<sweep id>`` added;
    with more than :data:`LABEL_SETTINGS` differing settings every label is ``learner@<sweep id>``."""
    recorded = set.intersection(*(set(c) for c in configs.values()))
    differing = sorted(k for k in recorded if len({c[k] for c in configs.values()}) > 1)
    if len(differing) > LABEL_SETTINGS:
        return {sweep: f"{learner}@{sweep}" for sweep in configs}
    short = [k.split(".", 1)[-1] for k in differing]
    names = [name if short.count(name) == 1 else key for key, name in zip(differing, short)]
    labels = {sweep: f"{learner} [{', '.join(f'{n}={c[k]}' for n, k in zip(names, differing))}]" if differing else learner
              for sweep, c in configs.items()}
    shared = {label for label in labels.values() if list(labels.values()).count(label) > 1}
    return {sweep: f"{label}@{sweep}" if label in shared else label for sweep, label in labels.items()}


def file_slug(label: str) -> str:
    """``label`` as a file-name part: ``pilco [horizon=30]`` -> ``pilco_horizon-30``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label.replace("=", "-")).strip("_")


def groups(runs: Sequence[RunRecord]) -> dict[str, dict[str, list[RunRecord]]]:
    """``task -> label -> runs`` (sorted by seed), tasks and labels in first-seen order."""
    out: dict[str, dict[str, list[RunRecord]]] = {}
    for r in runs:
        out.setdefault(r.task, {}).setdefault(r.label, []).append(r)
    for by_label in out.values():
        for rs in by_label.values():
            rs.sort(key=lambda r: r.seed)
    return out


# ---------------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------------


def _range(values: Sequence[float]) -> tuple[float, float, float]:
    if not values:
        return (math.nan, math.nan, math.nan)
    arr = np.asarray(values, dtype=np.float64)
    return float(np.median(arr)), float(arr.min()), float(arr.max())


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
    trials = _range([r.trials_to_success for r in solved if r.trials_to_success is not None])
    wall = _range([r.wall_seconds for r in runs])
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


RUNS_FIELDS = ["task", "learner", "seed", "counted", "solved", "time_to_success_s", "trials_to_success", "interaction_used_s",
               "episodes", "wall_seconds", "stop_reason", "status", "run_id"]


def run_rows(task: str, label: str, runs: Sequence[RunRecord], counted: bool = True) -> list[dict[str, Any]]:
    """One row per run; an unsolved run has no time to success (``nan``), only the interaction it
    used before it stopped. ``counted=False``: runs stopped before their limit (KILLED, or RUNNING
    at the time of the report), listed with the interaction and trials they reached but in no
    statistic; their label gets :data:`~harness.figures.STOPPED_SUFFIX`."""
    from harness.figures import STOPPED_SUFFIX

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
            trials = _num(r["trials_to_success"]) if r["solved"] else "–"
        else:
            time = f"> {r['interaction_used_s']:.1f} (*stopped*, unsolved so far)"
            trials = f"– ({_num(r['episodes'])} so far)"
        lines.append(f"| {r['learner']} | {r['seed']} | {'yes' if r['solved'] else 'no'} | {time} | {trials} "
                     f"| {r['interaction_used_s']:.1f} | {r['wall_seconds']:.0f} | {r['stop_reason']} | `{r['run_id'][:8]}` |")
    return "\n".join(lines) + "\n"


#: per-trial timings a learner or the runner may log (seconds), as (metric, column) in table order
WALL_PARTS = (("model_train_seconds", "model_training"), ("policy_opt_seconds", "policy_search"), ("eval_seconds", "evaluation"))


def wall_breakdown(series: Sequence[dict[str, dict[int, float]]]) -> dict[str, Any]:
    """Where the wall time of some runs went, per trial.

    ``series``: per run, ``metric -> {step: value}`` for ``wall_seconds`` (cumulative) and the
    :data:`WALL_PARTS`. A trial's wall time is the increase of ``wall_seconds`` over the previous
    trial (the first trial's includes the set-up and initial rollouts). Returns the number of
    trials (``policies``: policies handed over), the median and range of the per-trial wall time,
    the median wall time of the runs' last trial, the total, and each part's share of the total (``nan`` where no run logs it;
    ``other`` = the rest: rollouts, logging, checkpoints)."""
    walls, last, total, parts = [], [], 0.0, {column: 0.0 for _, column in WALL_PARTS}
    logged = {column: False for _, column in WALL_PARTS}
    for metrics in series:
        cumulative = metrics.get("wall_seconds", {})
        steps = sorted(cumulative)
        per_trial = np.diff([0.0] + [cumulative[s] for s in steps])
        if per_trial.size:
            walls += per_trial.tolist()
            last.append(float(per_trial[-1]))
            total += float(per_trial.sum())
        for key, column in WALL_PARTS:
            values = [metrics.get(key, {}).get(s) for s in steps]
            values = [v for v in values if v is not None and math.isfinite(v)]
            if values:
                logged[column] = True
                parts[column] += float(sum(values))
    wall = _range(walls)
    row: dict[str, Any] = {"policies": len(walls), "wall_per_trial_median_s": wall[0], "wall_per_trial_min_s": wall[1],
                           "wall_per_trial_max_s": wall[2], "last_trial_wall_median_s": _range(last)[0], "total_wall_s": total}
    for _, column in WALL_PARTS:
        row[f"share_{column}"] = parts[column] / total if logged[column] and total > 0 else math.nan
    accounted = sum(parts.values())
    row["share_other"] = (total - accounted) / total if total > 0 else math.nan
    return row


def walltime_markdown(task: str, rows: Sequence[dict[str, Any]]) -> str:
    pct = lambda v: "–" if math.isnan(v) else f"{100 * v:.0f} %"  # noqa: E731
    lines = [f"## {task}: where the wall time goes", "",
             "Per trial = one policy handed over: the learner's work for it (PILCO: GP training, policy search), the harness's "
             "evaluation episodes, the trial's rollout and the logging. Wall per trial grows with the data, so the "
             "last trial's is given too. Shares are of the total wall time of all trials of the row's runs; '–' = not "
             "logged by that learner (or by runs made before `eval_seconds` was logged, whose evaluation is then in "
             "'other'). Machine: shared, 2 cores, one torch thread per run; wall times are upper bounds.", "",
             "| learner | runs | policies | wall per trial, median [range] (s) | last trial (s, median) | total (h) "
             "| GP training | policy search | evaluation | other |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['learner']} | {r['runs']} | {r['policies']} | {_fmt_range(r['wall_per_trial_median_s'], r['wall_per_trial_min_s'], r['wall_per_trial_max_s'])} "
                     f"| {_num(r['last_trial_wall_median_s'])} | {r['total_wall_s'] / 3600:.2f} | {pct(r['share_model_training'])} "
                     f"| {pct(r['share_policy_search'])} | {pct(r['share_evaluation'])} | {pct(r['share_other'])} |")
    return "\n".join(lines) + "\n"


def representative_run(runs: Sequence[RunRecord]) -> RunRecord | None:
    """The solved run with the median time to success (lower median), else the longest run."""
    solved = sorted((r for r in runs if r.solved and r.time_to_success is not None), key=lambda r: (r.time_to_success, r.seed))
    if solved:
        return solved[(len(solved) - 1) // 2]
    return max(runs, key=lambda r: (r.interaction_seconds, -r.seed), default=None)


def _run_artifacts(client, run_id: str, what: str, task: str, label: str, role: str) -> list:
    """The run's top-level artifacts; if it has none (its artifact folder was not copied with the
    database), a :class:`MissingArtifactsWarning` says that ``what`` was not written."""
    entries = client.list_artifacts(run_id)
    if not entries:
        warnings.warn(f"{what} of {task} / {label} not written: its {role} run {run_id} has no artifacts in the store "
                      "(was its artifact folder copied with the database?)", MissingArtifactsWarning, stacklevel=3)
    return entries


def last_prediction_plot(client, run_id: str, entries: Sequence | None = None) -> str | None:
    """Artifact path of the run's last ``prediction_trial*.png`` (PILCO logs one per trial);
    ``entries``: the run's top-level artifacts, if already listed."""
    found: list[str] = []
    for entry in client.list_artifacts(run_id) if entries is None else entries:
        if entry.is_dir and entry.path.startswith("trial"):
            found += [a.path for a in client.list_artifacts(run_id, entry.path)
                      if Path(a.path).name.startswith("prediction_trial") and a.path.endswith(".png")]
    return max(found, key=lambda p: Path(p).name, default=None)


def copy_prediction_plot(client, task: str, label: str, runs: Sequence[RunRecord], out: Path) -> Path | None:
    """Download the representative run's last prediction plot to ``prediction_<task>_<label>.png``."""
    import shutil
    import tempfile

    run = representative_run(runs)
    if run is None:
        return None
    entries = _run_artifacts(client, run.run_id, "prediction plot", task, label, "representative")
    if not entries:
        return None
    name = last_prediction_plot(client, run.run_id, entries)
    if name is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        local = client.download_artifacts(run.run_id, name, tmp)
        target = out / f"prediction_{task}_{file_slug(label)}.png"
        shutil.copyfile(local, target)
    return target


def test_rows(client, task: str, label: str, runs: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """One row per run whose saved policy was tested with ``harness eval`` (its ``test_*`` metrics)."""
    rows = []
    for r in sorted(runs, key=lambda r: r.seed):
        metrics = client.get_run(r.run_id).data.metrics
        if "test_success_rate" in metrics:
            rows.append({"task": task, "learner": label, "seed": r.seed, "solved": r.solved,
                         "finished": r.status in ("FINISHED", "FAILED"),
                         "test_episodes": int(metrics.get("test_episodes", 0)),
                         "test_success_rate": metrics["test_success_rate"], "run_id": r.run_id})
    return rows


def test_markdown(task: str, rows: Sequence[dict[str, Any]]) -> str:
    lines = [f"# `{task}`: saved policies tested on fresh episodes (`harness eval RUN_ID --episodes N`)", "",
             "Test episodes start from the task's initial distribution on a new environment (seed 12345 + i); they are "
             "not interaction. Success: the task's own rule. The histogram of final distances from the goal of the "
             f"representative tested run is `fig4b_{task}_<learner>.png` (the paper's Fig. 4b for the unicycle).", "",
             "| learner | seed | solved in training | test episodes | test success rate | run |", "|---|---|---|---|---|---|"]
    for r in rows:
        training = "yes" if r["solved"] else ("no" if r["finished"] else "no (run stopped before its limit)")
        lines.append(f"| {r['learner']} | {r['seed']} | {training} | {r['test_episodes']} "
                     f"| {100 * r['test_success_rate']:.1f} % | `{r['run_id'][:8]}` |")
    return "\n".join(lines) + "\n"


def copy_test_histogram(client, task: str, label: str, runs: Sequence[RunRecord], tested: Sequence[dict[str, Any]],
                        out: Path) -> Path | None:
    """The final-distance histogram of the representative run if it was tested, else of the first tested run."""
    import shutil
    import tempfile

    ids = [row["run_id"] for row in tested]
    if not ids:
        return None
    rep = representative_run(runs)
    run_id = rep.run_id if rep is not None and rep.run_id in ids else ids[0]
    if not _run_artifacts(client, run_id, "test histogram", task, label, "tested"):
        return None
    names = [a.path for a in client.list_artifacts(run_id, "test") if a.path.endswith("test_final_distance.png")]
    if not names:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        local = client.download_artifacts(run_id, names[0], tmp)
        target = out / f"fig4b_{task}_{file_slug(label)}.png"
        shutil.copyfile(local, target)
    return target


def fmt_seconds(value: float) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if math.isinf(value):
        return "∞"
    return f"{value:.1f}"


def _fmt_stat(point: float, low: float, high: float) -> str:
    if math.isnan(point):
        return "–"
    if math.isinf(point):
        return f"not reached [{fmt_seconds(low)}, {fmt_seconds(high)}]"
    return f"{point:.1f} [{fmt_seconds(low)}, {fmt_seconds(high)}]"


def _fmt_bounds(low: float, high: float, stopped: int, finished: int) -> str:
    """``'≥ 63.0 (2 stopped of 4)'``, ``'40.0–55.0 (…)'``, or ``'–'`` without stopped runs."""
    if not stopped:
        return "–"
    runs = f"({stopped} stopped of {stopped + finished})"
    if low == high:
        return f"{fmt_seconds(low)} {runs}"
    return f"≥ {fmt_seconds(low)} {runs}" if math.isinf(high) else f"{fmt_seconds(low)}–{fmt_seconds(high)} {runs}"


def _num(value: float) -> str:
    """Integers as such (``305``), other numbers with one decimal (``1.5``)."""
    return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"


def _seconds(value: float) -> str:
    return f"{value:.1f}"


def _fmt_range(med: float, lo: float, hi: float, fmt=_num) -> str:
    if math.isnan(med):
        return "–"
    return f"{fmt(med)} [{fmt(lo)}–{fmt(hi)}]"


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
    lines = [f"## {task}", "", STAT_NOTE, "",
             "| learner | solved | median time to success [95 % CI] (s) | IQM [95 % CI] (s) | trials to success | unsolved at (s) "
             "| wall time (s) | errors | median with the stopped runs (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        censored = "–" if math.isnan(r["unsolved_interaction_min_s"]) else (
            f"{r['unsolved_interaction_min_s']:.1f}" if r["unsolved_interaction_min_s"] == r["unsolved_interaction_max_s"]
            else f"{r['unsolved_interaction_min_s']:.1f}–{r['unsolved_interaction_max_s']:.1f}")
        lines.append(
            f"| {r['learner']} | {r['solved']}/{r['runs']} "
            f"| {_fmt_stat(r['median_time_to_success_s'], r['median_ci_low_s'], r['median_ci_high_s'])} "
            f"| {_fmt_stat(r['iqm_time_to_success_s'], r['iqm_ci_low_s'], r['iqm_ci_high_s'])} "
            f"| {_fmt_range(r['trials_to_success_median'], r['trials_to_success_min'], r['trials_to_success_max'])} "
            f"| {censored} | {_fmt_range(r['wall_seconds_median'], r['wall_seconds_min'], r['wall_seconds_max'], fmt=_seconds)} | {r['errors']} "
            f"| {_fmt_bounds(r['median_with_stopped_low_s'], r['median_with_stopped_high_s'], r['stopped'], r['runs'])} |"
        )
    return "\n".join(lines) + "\n"


def table1_rows(runs_by_task: dict[str, dict[str, list[RunRecord]]], learner: str,
                incomplete: Sequence[RunRecord] = ()) -> list[dict[str, Any]]:
    """Table 1 measured for ``learner`` on the paper's tasks that were run: a row per task and row
    label (several where the learner ran on a task in differently configured sweeps)."""
    rows = []
    for task in PAPER_TABLE1:
        counted = {label: runs for label, runs in runs_by_task.get(task, {}).items() if runs and runs[0].learner == learner}
        labels = dict.fromkeys([*counted, *(r.label for r in incomplete if r.task == task and r.learner == learner)])
        for label in labels:
            runs = counted.get(label, [])
            stopped = [r for r in incomplete if r.task == task and r.label == label]
            rows.append(_table1_row(task, label, runs, stopped))
    return rows


def _table1_row(task: str, label: str, runs: Sequence[RunRecord], stopped: Sequence[RunRecord]) -> dict[str, Any]:
    paper_task, p_state, p_trials, p_exp, p_params = PAPER_TABLE1[task]
    solved = [r for r in runs if r.solved]
    dims = sorted({r.state_dim for r in [*runs, *stopped] if r.state_dim is not None})
    return {
        "task": task, "learner": label, "paper_task": paper_task, "runs": len(runs), "solved": len(solved),
        "stopped": len(stopped),
        "stopped_episodes": _range([r.episodes for r in stopped if r.episodes is not None]),
        "stopped_interaction_s": _range([r.interaction_seconds for r in stopped]),
        "state_dim": "/".join(str(d) for d in dims) or "?",
        "trials": _range([r.trials_to_success for r in solved if r.trials_to_success is not None]),
        "experience_s": _range([r.time_to_success for r in solved if r.time_to_success is not None]),
        "policy_parameters": _range([r.policy_parameters for r in [*runs, *stopped] if r.policy_parameters is not None]),
        "paper": {"state": p_state, "trials": p_trials, "experience": p_exp, "parameters": p_params},
    }


def table1_markdown(rows: Sequence[dict[str, Any]], learner: str) -> str:
    lines = [
        f"# Table 1 (Deisenroth & Rasmussen, ICML 2011): measured for `{learner}`, median [min–max] over seeds",
        "",
        "Trials and experience are over the **solved** runs only; the `solved` column says how many of "
        "the runs that is (unsolved runs have no time to success; see the comparison tables for "
        "statistics that count them). Trials = interaction episodes up to the first solved evaluation, "
        "the initial random ones included. Experience = interaction time to success (system seconds). "
        "Parameters = the policy's parameter count logged by the learner (`policy_parameters`). "
        "Runs stopped before their limit (KILLED or still running, e.g. at the end of a session) are not counted; "
        "they are listed under the table with the trials and interaction they reached, unsolved so far.",
        "",
        "| task | solved | state space (ours / paper) | # trials (ours / paper) | experience in s (ours / paper) | policy parameters (ours / paper) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        p = r["paper"]
        params = r["policy_parameters"]
        variant = f", `{r['learner']}`" if r["learner"] != learner else ""
        lines.append(
            f"| {r['task']} ({r['paper_task']}){variant} | {r['solved']}/{r['runs']} | R^{r['state_dim']} / {p['state']} "
            f"| {_fmt_range(*r['trials'])} / {p['trials']} | {_fmt_range(*r['experience_s'], fmt=_seconds)} / {p['experience']} "
            f"| {'R^' + _fmt_range(*params) if not math.isnan(params[0]) else '–'} / {p['parameters']} |"
        )
    if not rows:
        lines.append(f"| (no runs of `{learner}` on cartpole, double-pendulum or unicycle in the selected sweeps) | | | | | |")
    notes = [r for r in rows if r["stopped"]]
    if notes:
        lines += ["", "Stopped before their limit, not solved so far (lower bounds, not results):", ""]
        for r in notes:
            variant = f" (`{r['learner']}`)" if r["learner"] != learner else ""
            lines.append(f"- {r['task']}{variant}: {r['stopped']} run(s) at {_fmt_range(*r['stopped_episodes'])} trials, "
                         f"{_fmt_range(*r['stopped_interaction_s'], fmt=_seconds)} s of interaction")
    return "\n".join(lines) + "\n"


def _flat_table1(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for r in rows:
        flat = {"task": r["task"], "learner": r["learner"], "paper_task": r["paper_task"], "runs": r["runs"], "solved": r["solved"],
                "stopped": r["stopped"], "state_dim": r["state_dim"]}
        for key in ("trials", "experience_s", "policy_parameters", "stopped_episodes", "stopped_interaction_s"):
            flat[f"{key}_median"], flat[f"{key}_min"], flat[f"{key}_max"] = r[key]
        flat.update({f"paper_{k}": v for k, v in r["paper"].items()})
        out.append(flat)
    return out


TABLE1_FIELDS = ["task", "learner", "paper_task", "runs", "solved", "stopped", "state_dim"] + [
    f"{key}_{part}" for key in ("trials", "experience_s", "policy_parameters", "stopped_episodes", "stopped_interaction_s")
    for part in ("median", "min", "max")
] + ["paper_state", "paper_trials", "paper_experience", "paper_parameters"]


def write_csv(path: Path, rows: Sequence[dict[str, Any]], fields: Sequence[str] | None = None) -> Path:
    """``rows`` as CSV (``inf``/``nan`` written as such); a header only if there are no rows."""
    fieldnames = list(rows[0]) if rows else list(fields or [])
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fieldnames)
        writer.writeheader()
        writer.writerows(rows)
    return path


def incomplete_status(record: RunRecord) -> str:
    """A not-counted run's status; a RUNNING run whose process is gone is said to be stale."""
    if record.status == "RUNNING" and process_alive(record.process) is False:
        host, pid, _ = record.process.rsplit(":", 2)
        return (f"RUNNING in the store, but its process (pid {pid} on {host}) is gone: it stopped without being "
                "marked; re-run its command to resume it")
    return record.status


def notes_markdown(data: ReportData) -> str:
    """``sweeps.md``: the sweeps used, and every run or cell not counted."""
    lines = ["# Sweeps behind these results", "", f"Tracking store: `{data.tracking_uri}`", ""]
    for s in data.sweeps:
        head = f"- sweep `{s.sweep_id}` (parent run `{s.parent_run_id}`, status {s.status}):" if s.parent_run_id else f"- `{s.sweep_id}`: {s.status}"
        lines += [head, f"  `{s.params.get('command', '?')}`"]
    lines.append("")
    errored = [r for r in data.runs if r.status == "FAILED"]
    if errored:
        lines += ["## Runs that raised (counted as unsolved)", ""]
        lines += [f"- {r.learner} on {r.task}, seed {r.seed} (run `{r.run_id}`): {r.error or 'FAILED'}" for r in errored]
        lines.append("")
    if data.incomplete:
        lines += ["## Runs not counted (still running or killed)", ""]
        lines += [f"- {r.learner} on {r.task}, seed {r.seed} (run `{r.run_id}`): {incomplete_status(r)}" for r in data.incomplete]
        lines.append("")
    if data.missing:
        lines += ["## Cells of the sweeps without any run (not counted)", ""]
        lines += [f"- sweep `{sid}`: {l} on {t}, seed {s}" for sid, (l, t, s) in data.missing]
        lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------------


def _json_safe(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in rows]


def read_literature(path: Path | None) -> list[dict[str, str]]:
    """Rows of ``literature_fig5.csv`` (``#`` lines are comments); a row without a source is an error."""
    if path is None or not Path(path).exists():
        return []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if line.strip() and not line.lstrip().startswith("#")))
    for row in rows:
        if not (row.get("source") or "").strip():
            raise HarnessError(f"{path}: the row {row.get('method')!r} has no source; every literature value needs a citable source")
        float(row["interaction_seconds"])
    return rows


def make_report(
    client,
    out: Path,
    sweep_ids: Sequence[str] | None = None,
    tracking_uri: str = "",
    table1_learner: str = "pilco",
    fig5_task: str = "cartpole",
    literature: Path | None = None,
    include_bench: bool = False,
) -> list[Path]:
    """Write every table and figure into ``out`` and return the written paths."""
    from harness import figures

    data = load(client, sweep_ids, tracking_uri, include_bench)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    by_task = groups(data.runs)
    stopped_by_task = groups(data.incomplete)

    all_rows: list[dict[str, Any]] = []
    for task in dict.fromkeys([*by_task, *stopped_by_task]):
        by_label, stopped = by_task.get(task, {}), stopped_by_task.get(task, {})
        labels = dict.fromkeys([*by_label, *stopped])  # a configuration whose runs are all stopped has a row too
        rows = [comparison_row(task, label, by_label.get(label, []), stopped=stopped.get(label, ())) for label in labels]
        all_rows += rows
        md = out / f"comparison_{task}.md"
        md.write_text(comparison_markdown(task, rows))
        written += [md, write_csv(out / f"comparison_{task}.csv", rows)]

    for task in dict.fromkeys([*by_task, *stopped_by_task]):
        rows = [row for label, runs in by_task.get(task, {}).items() for row in run_rows(task, label, runs)]
        rows += [row for label, runs in stopped_by_task.get(task, {}).items() for row in run_rows(task, label, runs, counted=False)]
        (out / f"runs_{task}.md").write_text(runs_markdown(task, rows))
        written += [out / f"runs_{task}.md", write_csv(out / f"runs_{task}.csv", rows, RUNS_FIELDS)]

    # plots and tests of saved policies: runs stopped before their limit have real policies too
    for task, by_label in groups([*data.runs, *data.incomplete]).items():
        tested: list[dict[str, Any]] = []
        for label, runs in by_label.items():
            plot = copy_prediction_plot(client, task, label, runs, out)
            if plot is not None:
                written.append(plot)
            label_tested = test_rows(client, task, label, runs)
            tested += label_tested
            histogram = copy_test_histogram(client, task, label, runs, label_tested, out)
            if histogram is not None:
                written.append(histogram)
        if tested:
            (out / f"test_{task}.md").write_text(test_markdown(task, tested))
            written += [out / f"test_{task}.md", write_csv(out / f"test_{task}.csv", tested)]

    t1 = table1_rows(by_task, table1_learner, data.incomplete)
    (out / "table1.md").write_text(table1_markdown(t1, table1_learner))
    written += [out / "table1.md", write_csv(out / "table1.csv", _flat_table1(t1), TABLE1_FIELDS)]

    lit = read_literature(literature if literature is not None else out / "literature_fig5.csv")
    fig5_rows = figures.fig5_data(by_task.get(fig5_task, {}), lit)
    written += [write_csv(out / "fig5.csv", fig5_rows), figures.plot_fig5(fig5_rows, out / "fig5.png", fig5_task)]

    for task in dict.fromkeys([*by_task, *stopped_by_task]):
        curves = {label: [history(client, r.run_id) for r in runs] for label, runs in by_task.get(task, {}).items()}
        stopped = {label + figures.STOPPED_SUFFIX: [history(client, r.run_id) for r in runs]
                   for label, runs in stopped_by_task.get(task, {}).items()}
        curves.update(stopped)
        table = figures.curve_table(curves, stopped=frozenset(stopped))
        written += [write_csv(out / f"curves_{task}.csv", table), figures.plot_curves(table, out / f"curves_{task}.png", task, curves)]

    for task in dict.fromkeys([*by_task, *stopped_by_task]):
        rows = []
        for runs_of, suffix in ((by_task.get(task, {}), ""), (stopped_by_task.get(task, {}), figures.STOPPED_SUFFIX)):
            for label, runs in runs_of.items():
                series = [metric_series(client, r.run_id, ("wall_seconds", *(key for key, _ in WALL_PARTS))) for r in runs]
                rows.append({"task": task, "learner": label + suffix, "runs": len(runs), **wall_breakdown(series)})
        (out / f"walltime_{task}.md").write_text(walltime_markdown(task, rows))
        written += [out / f"walltime_{task}.md", write_csv(out / f"walltime_{task}.csv", rows)]

    (out / "sweeps.md").write_text(notes_markdown(data))
    written.append(out / "sweeps.md")

    if sweep_ids:
        for sweep in (s for s in data.sweeps if s.parent_run_id):  # bench groups have no parent run
            rows = [r for r in all_rows if sweep.sweep_id in r["sweep_id"].split(",")]
            import pandas as pd

            client.log_table(sweep.parent_run_id, data=pd.DataFrame(_json_safe(rows)), artifact_file="report/comparison.json")
            for path in written:
                if path.suffix in (".md", ".png"):
                    client.log_artifact(sweep.parent_run_id, str(path), "report")
    return written


def metric_series(client, run_id: str, keys: Sequence[str]) -> dict[str, dict[int, float]]:
    """``key -> {step: value}`` of a run's metric histories (empty where a key was never logged)."""
    return {key: {m.step: m.value for m in client.get_metric_history(run_id, key)} for key in keys}


def history(client, run_id: str) -> dict[str, np.ndarray]:
    """Per hand-over: ``interaction_seconds``, ``eval_success_rate``, ``eval_cost`` aligned on the step."""
    series = metric_series(client, run_id, ("interaction_seconds", "eval_success_rate", "eval_cost"))
    steps = sorted(set(series["interaction_seconds"]) & set(series["eval_success_rate"]) & set(series["eval_cost"]))
    return {key: np.array([series[key][s] for s in steps], dtype=np.float64) for key in series}


__all__ = ["make_report", "load", "comparison_row", "table1_rows", "read_literature"]
