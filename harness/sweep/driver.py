"""The sweep driver: opens the sweep's parent runs, finds what is left to run, feeds the cells to a
pool with at most ``workers`` in flight, and closes the parents with how their cells ended."""

from __future__ import annotations

import json
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

from harness.errors import OptionError
from harness.interrupts import StopRequests
from harness.store import RunReader, Store, layout
from harness.sweep import pools
from harness.sweep.cell import CellJob, CellOutcome
from harness.sweep.lease import grant, revoke
from harness.sweep.progress import SilentSweepProgress, SweepProgress, TrialWatcher
from harness.sweep.spec import Cell, SweepSpec, format_seeds, validate


#: times a cell whose worker was lost (its process or its Ray node died) runs again in one invocation
MAX_CELL_RETRIES = 2

#: the statuses of a run a lost worker can leave for the driver to resume
UNFINISHED = ("RUNNING", "KILLED")


@dataclass(frozen=True)
class CellRetry:
    """A cell run again after its worker was lost: where (``node``: the Ray node id, if known), why,
    and the run it resumes (``None``: the worker died before its run existed) after ``trials`` stored trials."""

    cell: Cell
    error: str
    run_id: str | None
    node: str | None
    trials: int

    def line(self) -> str:
        where = f" on node {self.node}" if self.node else ""
        then = f"resumed run {self.run_id} after trial {self.trials}" if self.run_id else "started again"
        return f"{self.cell.label}: worker lost{where} ({self.error}); {then}"


@dataclass
class SweepResult:
    sweep_id: str
    #: per task: (experiment id, parent run id) of the sweep's parent run in that task
    parents: dict[str, tuple[str, str]]
    tracking_uri: str
    outcomes: list[CellOutcome]
    #: cells left unstarted by a stop request (``kill -USR1`` to the driver)
    unstarted: list[Cell] = field(default_factory=list)
    #: cells run again because their worker was lost, in the order it happened
    retries: list[CellRetry] = field(default_factory=list)

    @property
    def not_started(self) -> int:
        return len(self.unstarted)

    @property
    def stopped_early(self) -> bool:
        """Whether a stop request ended the sweep before every cell had run (the parent runs are KILLED)."""
        return bool(self.with_status("stopped")) or self.not_started > 0

    def with_status(self, status: str, task: str | None = None) -> list[CellOutcome]:
        return [o for o in self.outcomes if o.status == status and task in (None, o.cell.task)]

    @property
    def failed(self) -> list[CellOutcome]:
        return self.with_status("failed")

    def parent_lines(self) -> list[str]:
        """``cartpole: run <id>`` per task (one line: a legacy sweep's single parent)."""
        by_run: dict[str, list[str]] = {}
        for task, (_, run_id) in self.parents.items():
            by_run.setdefault(run_id, []).append(task)
        return [f"{', '.join(tasks)}: run {run_id}" for run_id, tasks in by_run.items()]


def open_parents(store: Store, spec: SweepSpec) -> dict[str, tuple[str, str]]:
    """The sweep's parent run per task, ``task -> (experiment id, run id)``, opened (RUNNING):
    a sweep begun in the legacy layout (one parent in the ``sweeps`` experiment) goes on there; any
    other has a parent in each task's experiment, created if missing."""
    legacy = store.experiment_id(layout.LEGACY_SWEEP_EXPERIMENT)
    found = store.sweep_parents(spec.sweep_id, legacy) if legacy is not None else []
    if found:
        store.set_status(found[0].run_id, "RUNNING")
        return dict.fromkeys(spec.tasks, (legacy, found[0].run_id))
    parents = {}
    for task in spec.tasks:
        experiment_id = store.ensure_experiment(layout.task_experiment(task))
        existing = store.sweep_parents(spec.sweep_id, experiment_id)
        if existing:
            run_id = existing[0].run_id
            store.set_status(run_id, "RUNNING")
        else:
            run_id = store.create_run(experiment_id, layout.sweep_parent_name(spec.sweep_id, task), {
                layout.SWEEP_TAG: spec.sweep_id, layout.ROLE_TAG: layout.ROLE_SWEEP, layout.TASK_TAG: task,
                layout.NOTE_TAG: (f"Sweep `{spec.sweep_id}`: its cells on {task} are this run's children. Run (and continue) it with\n\n"
                                  f"    {spec.command()}\n\n`harness report --sweep {spec.sweep_id}` compares them with the other "
                                  f"runs on {task} in the run `{layout.comparison_name(task)}`.")},
                params=parent_params(spec, task))
        parents[task] = (experiment_id, run_id)
    return parents


def parent_params(spec: SweepSpec, task: str) -> dict[str, Any]:
    """The sweep's spec as its parent's params (``cells``: the cells in ``task``)."""
    return {
        "learners": ",".join(spec.learners),
        "tasks": ",".join(spec.tasks),
        "seeds": format_seeds(spec.seeds),
        "set": json.dumps(spec.canonical()["set"]),
        "max_trials": spec.max_trials,
        "budget_seconds": spec.budget_seconds,
        "eval_episodes": spec.eval_episodes,
        "cells": sum(c.task == task for c in spec.cells()),
        "command": spec.command(),
    }


def _cell_of(run: RunReader) -> Cell | None:
    cell = run.cell
    return None if cell is None else Cell(*cell)


def _record_failed_child(store: Store, job: CellJob, error: str) -> str:
    """A FAILED child for a cell whose worker died before its run existed (so it is never lost)."""
    cell = job.cell
    run_id = store.create_run(job.experiment_id, layout.run_name(cell.learner, cell.task, cell.seed), {
        layout.PARENT_TAG: job.parent_run_id, layout.SWEEP_TAG: job.sweep_id, layout.ROLE_TAG: layout.ROLE_CELL,
        layout.LEARNER_TAG: cell.learner, layout.TASK_TAG: cell.task, layout.SEED_TAG: str(cell.seed)})
    store.set_tags(run_id, {layout.ERROR_TAG: error, layout.STOP_REASON_TAG: "failed", layout.RESUMABLE_TAG: "false",
                            layout.NOTE_TAG: f"**Failed** before its run started: {error}"})
    store.set_status(run_id, "FAILED")
    return run_id


def _mark_crashed(store: Store, job: CellJob, error: str) -> str:
    """The run a dead worker left unfinished is marked KILLED with the error (the next invocation
    continues it from its last checkpoint); without one, a FAILED child records the error. The
    cell's lease is revoked first: a worker that lives on writes nothing more."""
    revoke(store, job.parent_run_id, job.cell)
    run = _newest_child(store, job, UNFINISHED)
    if run is None:
        return _record_failed_child(store, job, error)
    _mark_lost(store, run, error)
    return run.run_id


def _mark_lost(store: Store, run: RunReader, error: str) -> None:
    """``run``, which a lost worker left unfinished, marked KILLED (resumable) with the error."""
    store.set_tags(run.run_id, {layout.ERROR_TAG: error, layout.RESUMABLE_TAG: "true",
                                layout.NOTE_TAG: f"**Stopped before its limit**: {error}. **Resumable**: the same sweep command continues it."})
    store.set_status(run.run_id, "KILLED")


def _retry_lost(store: Store, job: CellJob, error: str, grace: float = 0.0) -> tuple[CellJob, CellRetry] | CellOutcome:
    """The job that runs a cell whose worker was lost again, resuming the run the worker left (if any);
    or, where that worker finished the cell's run before the loss came to light, the cell's outcome.

    The lost worker may live on (a Ray node cut off, not dead; a raylet killed before its workers,
    which run in process groups of their own): its lease is revoked first, so it writes nothing more,
    and after ``grace`` seconds (a write it began before lands) the run it left, even one it created
    just before, is the one resumed. A worker that lived on long enough may have marked its run KILLED
    itself (resumed like a RUNNING one) or finished it before the driver heard of the loss (node
    deaths are noticed in seconds, a short trial ends sooner): that run is the cell's outcome, and
    nothing runs again."""
    revoke(store, job.parent_run_id, job.cell)
    if grace > 0:
        time.sleep(grace)
    left = _newest_child(store, job, (*UNFINISHED, "FINISHED"))
    if left is None:
        return job, CellRetry(job.cell, error, None, None, 0)
    if left.status == "FINISHED":
        return _finished_outcome(left, job)
    _mark_lost(store, left, error)
    retry = CellRetry(job.cell, error, left.run_id, left.tags.get(layout.NODE_TAG), len(left.history(layout.INTERACTION_SECONDS)))
    return replace(job, resume_run_id=left.run_id), retry


def _finished_outcome(run: RunReader, job: CellJob) -> CellOutcome:
    """The ``finished`` outcome of a cell whose run a lost worker finished, read back from the store."""
    return CellOutcome(job.cell, "finished", run.run_id, solved=run.solved, interaction_time_to_success=run.time_to_success,
                       interaction_seconds=run.reached(layout.INTERACTION_SECONDS), wall_seconds=run.reached(layout.WALL_SECONDS),
                       stop_reason=run.tags.get(layout.STOP_REASON_TAG, ""), resumed=job.resume_run_id is not None)


def _newest_child(store: Store, job: CellJob, statuses: tuple[str, ...]) -> RunReader | None:
    """The newest child run of ``job``'s cell with one of ``statuses``, if any. A cell's children are
    its runs of earlier invocations (FINISHED ones make a cell skipped, so it has none of those) and
    of this one, so the newest unfinished one is the run a resumed cell must continue."""
    cell = job.cell
    found = store.children(job.parent_run_id, job.experiment_id, (
        f"tags.learner = '{cell.learner}' AND tags.task = '{cell.task}' AND tags.seed = '{cell.seed}'"))
    found = [r for r in found if r.status in statuses]
    return max(found, key=lambda r: r.start_time) if found else None


def _running_child(store: Store, job: CellJob) -> str | None:
    """The newest child run of ``job``'s cell still marked RUNNING, if any."""
    run = _newest_child(store, job, ("RUNNING",))
    return None if run is None else run.run_id


def run_sweep(
    spec: SweepSpec,
    tracking_uri: str | None = None,
    executor: pools.Executor = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: SweepProgress | None = None,
) -> SweepResult:
    """Run (or resume) ``spec`` and return every cell's outcome; failed cells do not raise.

    ``kill -USR1`` to this process (on its main thread) drains the sweep: no more cells start,
    running local cells stop after their trial in progress (``stopped`` outcomes; Ray cells run
    to their end), and the result comes back with :attr:`SweepResult.stopped_early`, the parent
    runs KILLED; the same spec run again continues.

    Everything the user can get wrong (plugins, options, limits, executor) is checked before the
    store is touched. ``workers`` defaults to :func:`~harness.sweep.pools.default_workers` (local)
    or to the Ray cluster's CPUs (``--address``) / the same default (embedded Ray).
    """
    pools.check_executor(executor)
    if workers is not None and workers < 1:
        raise OptionError(f"--workers must be >= 1, got {workers}")
    if address is not None and executor != "ray":
        raise OptionError("--address is for --executor ray")
    setups = validate(spec)
    progress = progress or SilentSweepProgress()

    store = Store(tracking_uri)
    sweep_id = spec.sweep_id
    parents = open_parents(store, spec)

    finished: dict[Cell, str] = {}
    newest: dict[Cell, RunReader] = {}
    for experiment_id, parent_run_id in dict.fromkeys(parents.values()):
        for run in store.children(parent_run_id, experiment_id):
            cell = _cell_of(run)
            if cell is None:
                continue
            if run.status == "FINISHED":
                finished[cell] = run.run_id
            if cell not in newest or run.start_time > newest[cell].start_time:
                newest[cell] = run
    interrupted = {c: r.run_id for c, r in newest.items() if r.status in ("KILLED", "RUNNING")}
    outcomes = [CellOutcome(c, "skipped", finished[c]) for c in spec.cells() if c in finished]
    jobs = deque(
        CellJob(c, setups[(c.learner, c.task)]["learner_options"], setups[(c.learner, c.task)]["task_options"],
                spec.max_trials, spec.budget_seconds, spec.eval_episodes, store.uri, *parents[c.task], sweep_id,
                setups[(c.learner, c.task)]["extra_params"], interrupted.get(c))
        for c in spec.cells() if c not in finished
    )
    result = SweepResult(sweep_id, parents, store.uri, outcomes)
    total = len(spec.cells())
    status = "FAILED"  # unless the loop completes; KILLED on Ctrl-C
    pool: pools.Pool | None = None
    stop = StopRequests.listen()  # kill -USR1: no new cells, the running ones stop after their trial
    try:
        if jobs:
            pool = pools.make_pool(executor, workers, address)
        progress.start(sweep_id, total, len(outcomes))
        if pool is not None:
            watcher = TrialWatcher(store, list(dict.fromkeys(parents.values())))
            _drive(pool, jobs, pool.workers, result, store, progress, watcher, stop)
        result.unstarted = [job.cell for job in jobs]  # some only after a stop request
        status = "FINISHED"
    except KeyboardInterrupt:
        status = "KILLED"
        raise
    finally:
        stop.restore()
        if pool is not None:
            pool.close(cancel=status != "FINISHED")
        progress.finish(result)
        _close_parents(store, spec, result, executor, status)
    return result


def _drive(pool: pools.Pool, jobs: deque, workers: int, result: SweepResult, store: Store, progress: SweepProgress,
           watcher: TrialWatcher | None = None, stop: StopRequests | None = None) -> None:
    """Run ``jobs`` with at most ``workers`` in flight. Once ``stop`` is set (a stop request), no
    more cells start and the running ones are asked to stop after their trial in progress; it
    returns when they have, leaving the cells not started in ``jobs``."""
    inflight: dict[Any, tuple[CellJob, float]] = {}
    durations: list[float] = []
    retried: dict[Cell, int] = {}
    draining = False

    def report() -> None:
        done = len(result.outcomes)
        if durations:
            mean = sum(durations) / len(durations)
            now = time.perf_counter()
            remaining = len(jobs) * mean + sum(max(mean - (now - t0), 0.0) for _, t0 in inflight.values())
            eta = remaining / workers
        else:
            eta = None
        progress.update(done, len(inflight), len(result.failed), eta)

    try:
        while (jobs and not draining) or inflight:
            if stop is not None and stop.is_set() and not draining:
                draining = True
                pool.request_stop()
            while jobs and len(inflight) < workers and not draining:
                job = jobs.popleft()
                job = replace(job, lease=grant(store, job.parent_run_id, job.cell))  # the one writer of its run
                inflight[pool.submit(job)] = (job, time.perf_counter())
            report()
            if watcher is not None:
                watcher.poll(progress)
            for handle in pool.wait(list(inflight), timeout=1.0):
                job, t0 = inflight.pop(handle)
                try:
                    outcome = pool.result(handle)
                except Exception as exc:  # the worker process itself died (crash, out of memory, killed, its node lost)
                    cause = (str(exc) if isinstance(exc, pools.WorkerProcessDied) else f"{type(exc).__name__}: {exc}").splitlines()[0]
                    retried_as = None
                    if pool.lost(exc) and retried.get(job.cell, 0) < MAX_CELL_RETRIES and not draining:
                        retried_as = _retry_lost(store, job, f"worker process died ({cause[:300]})", pool.fence_grace)
                    if isinstance(retried_as, tuple):
                        again, retry = retried_as
                        retried[job.cell] = retried.get(job.cell, 0) + 1
                        result.retries.append(retry)
                        progress.cell_retried(retry)
                        jobs.appendleft(again)
                        continue
                    if isinstance(retried_as, CellOutcome):  # the lost worker had finished the cell's run
                        outcome = retried_as
                    else:
                        tries = f" (ran {retried[job.cell] + 1} times)" if job.cell in retried else ""
                        error = f"worker process died ({cause}){tries}; re-run the sweep to retry"
                        outcome = CellOutcome(job.cell, "failed", _mark_crashed(store, job, error), error=error)
                if outcome.status == "failed" and outcome.run_id is None:
                    outcome.run_id = _record_failed_child(store, job, outcome.error)
                durations.append(time.perf_counter() - t0)
                result.outcomes.append(outcome)
                progress.cell_done(outcome)
    except KeyboardInterrupt:
        # stop the running cells (each normally marks its run KILLED itself); a cell stopped before it
        # could (a force-killed process, a Ray task whose result came back cancelled first) is marked here
        pool.close(cancel=True)
        for job, _ in inflight.values():
            run_id = _running_child(store, job)
            if run_id is not None:
                store.set_status(run_id, "KILLED")
        raise
    report()


def _close_parents(store: Store, spec: SweepSpec, result: SweepResult, executor: str, status: str) -> None:
    """Each parent gets its cells' counts (tags and metrics, so that the runs table shows them) and its
    status: KILLED for a sweep stopped (Ctrl-C, or a stop request that left cells of it stopped or
    unstarted), FAILED where a cell of it failed (or the driver did), else FINISHED."""
    for experiment_id, parent_run_id in dict.fromkeys(result.parents.values()):
        tasks = [t for t, parent in result.parents.items() if parent == (experiment_id, parent_run_id)]
        of = {s: sum(len(result.with_status(s, t)) for t in tasks) for s in ("finished", "failed", "skipped", "stopped")}
        total = sum(c.task in tasks for c in spec.cells())
        unstarted = sum(c.task in tasks for c in result.unstarted)
        counts = dict(zip(layout.CELL_COUNT_TAGS, (total, of["finished"] + of["skipped"], of["failed"], of["stopped"])))
        own = status
        if status == "FINISHED":
            own = "KILLED" if of["stopped"] or unstarted else "FAILED" if of["failed"] else "FINISHED"
        retries = [r.line() for r in result.retries if r.cell.task in tasks]
        counts[layout.RETRIED_TAG] = len(retries)
        try:
            store.set_tags(parent_run_id, {**counts, layout.EXECUTOR_TAG: executor,
                                           **({layout.RETRIES_TAG: "\n".join(retries)[:5000]} if retries else {})})
            store.log_metrics(parent_run_id, {key.split(".", 1)[1]: float(n) for key, n in counts.items()})
        finally:
            store.set_status(parent_run_id, own)
