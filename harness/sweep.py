"""Sweeps: the cross product learners x tasks x seeds, run by a local process pool or by Ray.

    harness sweep --learners pilco,sac --tasks cartpole --seeds 0-9 [--executor local|ray] [--workers N]

**MLflow layout.** One experiment, ``sweeps``, holds every sweep::

    parent run "sweep-<id>"              tags harness.sweep_id=<id>, harness.role=sweep; params: the spec
      child run "<learner>-<task>-s<seed>" tags mlflow.parentRunId, harness.sweep_id, harness.role=cell,
                                           learner, task, seed; params: the runner's + spec.* (task sizes)

A sweep spans tasks, and MLflow nests children under their parent only inside one experiment, so
the sweep gets its own experiment rather than the per-task ones ``harness bench`` uses.

**Identity and resuming.** The sweep id is a hash of the spec (learners, tasks, seeds as sets;
the ``--set`` pairs; the limits). Running the same spec again finds the same parent run and
skips the cells that have a FINISHED child. A cell whose newest child was interrupted (KILLED,
or RUNNING left by a driver that died) continues in that child from its last per-trial
checkpoint (:mod:`harness.checkpoint`) if its learner supports resuming and a checkpoint exists;
every other unfinished cell (FAILED, or nothing to resume from) runs again as a new child. Old
children stay; the report uses the newest FINISHED child of each cell. A failed cell is reported
and never stops the others.

**Creation order.** With a fresh SQLite store, concurrent workers race on schema creation
(harness-reference §3.4): the driver opens the store, creates the experiment and the parent run,
and hands the tracking URI, experiment id and parent run id to the workers, which only create
their own runs.

**Workers.** Every cell runs in a fresh, single-threaded process (local: one process started
with the spawn method per cell; Ray: ``max_calls=1``), so its result never depends on what ran
before it (global RNGs, torch state). A learner that raises fails its own cell only. A cell whose
*process* dies (crash, out of memory, killed) is reported failed with its run marked KILLED, and
the next invocation continues it from its checkpoint; the cells beside it go on. The driver keeps at most
``workers`` cells in flight; that bounded feeding is the only scheduling done here.

**Stopping.** Ctrl-C or SIGTERM to the driver stops the running cells at once (each run KILLED,
resumable). ``kill -USR1 DRIVER_PID`` drains instead: no more cells start, and each running
local cell stops once its trial in progress is stored (Ray tasks cannot be signalled: they run to
their end). Either way the same command continues the sweep.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import tempfile
import time
import traceback
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

from harness.errors import HarnessError, OptionError
from harness.interrupts import (STOP_AFTER_TRIAL, StopRequested, StopRequests, catch_stop_requests_early,
                                terminate_as_interrupt)

SWEEP_EXPERIMENT = "sweeps"
SWEEP_TAG = "harness.sweep_id"
ROLE_TAG = "harness.role"
ERROR_TAG = "harness.error"
Executor = Literal["local", "ray"]


# ---------------------------------------------------------------------------------------------
# the spec
# ---------------------------------------------------------------------------------------------


def parse_names(text: str, what: str) -> tuple[str, ...]:
    """``"pilco, sac"`` -> ``("pilco", "sac")`` (order kept, duplicates dropped)."""
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise OptionError(f"--{what} expects a comma-separated list, got {text!r}")
    return names


def parse_seeds(text: str) -> tuple[int, ...]:
    """``"0-4,10"`` -> ``(0, 1, 2, 3, 4, 10)``; ranges are inclusive."""
    seeds: list[int] = []
    for part in (p.strip() for p in str(text).split(",")):
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not match:
            raise OptionError(f"--seeds expects numbers and ranges like 0-9 or 0,3,5-7; got {text!r}")
        lo = int(match.group(1))
        hi = int(match.group(2)) if match.group(2) is not None else lo
        if hi < lo:
            raise OptionError(f"--seeds range {part!r} is empty (write low-high)")
        seeds.extend(range(lo, hi + 1))
    return tuple(dict.fromkeys(seeds))


def format_seeds(seeds: Iterable[int]) -> str:
    """``(0, 1, 2, 5)`` -> ``"0-2,5"`` (the inverse of :func:`parse_seeds` on sorted seeds)."""
    out: list[str] = []
    ordered = sorted(set(seeds))
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        out.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(out)


@dataclass(frozen=True)
class Cell:
    """One (learner, task, seed) of a sweep."""

    learner: str
    task: str
    seed: int

    @property
    def label(self) -> str:
        return f"{self.learner}-{self.task}-s{self.seed}"


@dataclass(frozen=True)
class SweepSpec:
    """What a sweep runs. ``assignments`` are the raw ``--set`` pairs, applied to every cell.

    A key ``NAME:key`` (``NAME`` a learner or task of the sweep) applies only to the cells of
    that learner or task, e.g. ``sac:learning_rate=1e-3``.
    """

    learners: tuple[str, ...]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]
    assignments: tuple[tuple[str, str], ...] = ()
    max_trials: int | None = None
    budget_seconds: float | None = None
    eval_episodes: int = 10

    def cells(self) -> list[Cell]:
        """Task-major, then learner, then seed (the order cells are started in)."""
        return [Cell(l, t, s) for t in self.tasks for l in self.learners for s in self.seeds]

    def canonical(self) -> dict[str, Any]:
        """The spec as plain data, independent of the order names and seeds were given in."""
        return {
            "learners": sorted(self.learners),
            "tasks": sorted(self.tasks),
            "seeds": sorted(self.seeds),
            "set": sorted(dict(self.assignments).items()),
            "max_trials": self.max_trials,
            "budget_seconds": self.budget_seconds,
            "eval_episodes": self.eval_episodes,
        }

    @property
    def sweep_id(self) -> str:
        """12 hex digits of the SHA-256 of :meth:`canonical`: same spec, same id."""
        blob = json.dumps(self.canonical(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()[:12]

    def command(self) -> str:
        """The ``harness sweep`` command line that reproduces this spec."""
        parts = ["harness sweep", f"--learners {','.join(self.learners)}", f"--tasks {','.join(self.tasks)}",
                 f"--seeds {format_seeds(self.seeds)}"]
        if self.max_trials is not None:
            parts.append(f"--max-trials {self.max_trials}")
        if self.budget_seconds is not None:
            parts.append(f"--budget-seconds {self.budget_seconds:g}")
        if self.eval_episodes != 10:
            parts.append(f"--eval-episodes {self.eval_episodes}")
        parts += [f"--set {k}={v}" for k, v in dict(self.assignments).items()]
        return " ".join(parts)

    def assignments_for(self, learner: str, task: str) -> list[tuple[str, str]]:
        """The ``--set`` pairs that apply to the cells of ``learner`` on ``task``, scope removed."""
        out = []
        for key, value in self.assignments:
            if ":" in key:
                scope, key = key.split(":", 1)
                if scope not in self.learners and scope not in self.tasks:
                    raise OptionError(
                        f"--set {scope}:{key}=...: '{scope}' is none of this sweep's learners "
                        f"({', '.join(self.learners)}) or tasks ({', '.join(self.tasks)})"
                    )
                if scope not in (learner, task):
                    continue
            out.append((key, value))
        return out


@dataclass(frozen=True)
class CellJob:
    """Everything a worker needs to run one cell (plain, picklable data)."""

    cell: Cell
    learner_options: dict[str, str]
    task_options: dict[str, str]
    max_trials: int | None
    budget_seconds: float | None
    eval_episodes: int
    tracking_uri: str
    experiment_id: str
    parent_run_id: str
    sweep_id: str
    extra_params: dict[str, Any] = field(default_factory=dict)
    #: an interrupted child of this cell to continue from its last checkpoint
    resume_run_id: str | None = None


@dataclass
class CellOutcome:
    """How one cell ended in this invocation (``skipped``: it had a FINISHED child already)."""

    cell: Cell
    status: Literal["finished", "failed", "skipped", "stopped"]
    run_id: str | None
    solved: bool = False
    interaction_time_to_success: float | None = None
    interaction_seconds: float = 0.0
    wall_seconds: float = 0.0
    stop_reason: str = ""
    error: str = ""
    resumed: bool = False

    def line(self) -> str:
        head = f"{self.cell.label}" + (" (resumed from its checkpoint)" if self.resumed else "")
        if self.status == "failed":
            return f"{head}: FAILED ({self.error})"
        if self.status == "skipped":
            return f"{head}: already finished (run {self.run_id})"
        if self.status == "stopped":
            return f"{head}: {self.stop_reason} (run {self.run_id} KILLED; the next invocation resumes it)"
        if self.solved:
            return f"{head}: solved after {self.interaction_time_to_success:.1f} s of interaction, wall {self.wall_seconds:.0f} s"
        return f"{head}: not solved ({self.stop_reason}) after {self.interaction_seconds:.1f} s, wall {self.wall_seconds:.0f} s"


@dataclass
class SweepResult:
    sweep_id: str
    parent_run_id: str
    experiment_id: str
    tracking_uri: str
    outcomes: list[CellOutcome]

    #: cells left unstarted by a stop request (``kill -USR1`` to the driver)
    not_started: int = 0

    @property
    def stopped_early(self) -> bool:
        """Whether a stop request ended the sweep before every cell had run (the parent run is KILLED)."""
        return bool(self.with_status("stopped")) or self.not_started > 0

    def with_status(self, status: str) -> list[CellOutcome]:
        return [o for o in self.outcomes if o.status == status]

    @property
    def failed(self) -> list[CellOutcome]:
        return self.with_status("failed")


# ---------------------------------------------------------------------------------------------
# validation (before anything is started or logged)
# ---------------------------------------------------------------------------------------------


def validate(spec: SweepSpec) -> dict[tuple[str, str], dict[str, Any]]:
    """Load every plugin, route and check every option for every (learner, task) pair.

    Returns, per pair, ``learner_options``, ``task_options`` (raw strings, as the runner takes
    them) and ``extra_params`` (the sweep command, logged with every child run). Raises a one-line
    :class:`~harness.errors.HarnessError` on the first problem.
    """
    from harness.discovery import load_learner, load_task
    from harness.runner import RunConfig, prepare, route_options

    if not spec.seeds:
        raise OptionError("--seeds is empty")
    setups: dict[tuple[str, str], dict[str, Any]] = {}
    for task in spec.tasks:
        load_task(task)  # unknown or broken plugins fail here, before any option is looked at
        for learner in spec.learners:
            load_learner(learner)
            pairs = spec.assignments_for(learner, task)
            try:
                to_learner, to_task = route_options(learner, task, pairs)
                prepare(RunConfig(learner, task, 0, to_learner, to_task, spec.max_trials, spec.budget_seconds, spec.eval_episodes))
            except OptionError as exc:
                raise OptionError(f"{exc} (in the sweep cell {learner} on {task}; scope a --set to one learner or task with NAME:key=value)") from None
            setups[(learner, task)] = {
                "learner_options": to_learner,
                "task_options": to_task,
                "extra_params": {"sweep.command": spec.command()},  # task sizes: every run logs them (runner.run_params)
            }
    return setups


def default_workers() -> int:
    """One cell per core, minus one core for the driver, MLflow writes and the system; at least 1.

    Cells are single-threaded; on this project's 2-core machines that is 1, so wall-clock numbers
    stay comparable with ``harness bench``. Interaction time (the benchmark's measure) is system
    time and does not depend on it.
    """
    return max(1, (os.cpu_count() or 1) - 1)


# ---------------------------------------------------------------------------------------------
# the worker side
# ---------------------------------------------------------------------------------------------


def _single_thread() -> None:
    """One thread per cell (cells run side by side; :func:`harness.threads.single_threaded`)."""
    from harness.threads import single_threaded

    single_threaded()


def run_cell(job: CellJob) -> CellOutcome:
    """Run one cell as a child of the sweep's parent run; never raises for a failing learner
    (SIGTERM to the worker raises ``KeyboardInterrupt``: the runner marks the child KILLED;
    SIGUSR1 stops it after the trial in progress: a ``stopped`` outcome, the child KILLED)."""
    catch_stop_requests_early()
    _single_thread()
    terminate_as_interrupt()
    from harness.errors import CheckpointError
    from harness.progress import SilentProgress
    from harness.runner import RunConfig, run
    from harness.tracking import MlflowTracker

    class CellTracker(MlflowTracker):
        """Adds the sweep's tags and the task sizes to the child run the runner starts."""

        def start(self, experiment, run_name, params, tags):
            return super().start(experiment, run_name, {**params, **job.extra_params},
                                 {**tags, SWEEP_TAG: job.sweep_id, ROLE_TAG: "cell"})

    cell = job.cell
    config = RunConfig(cell.learner, cell.task, cell.seed, dict(job.learner_options), dict(job.task_options),
                       job.max_trials, job.budget_seconds, job.eval_episodes)

    def new_tracker() -> CellTracker:
        return CellTracker(job.tracking_uri, parent_run_id=job.parent_run_id, experiment_id=job.experiment_id)

    tracker = new_tracker()
    resumed = False
    try:
        if job.resume_run_id is not None:
            try:
                result = run(config, tracker=tracker, progress=SilentProgress(), resume_run_id=job.resume_run_id)
                resumed = True
            except CheckpointError:  # no checkpoint, learner cannot resume, or other settings: start afresh
                if tracker.run_id is not None and tracker.client.get_run(tracker.run_id).info.status == "RUNNING":
                    tracker.client.set_terminated(tracker.run_id, "KILLED")
                tracker = new_tracker()
                result = run(config, tracker=tracker, progress=SilentProgress())
        else:
            result = run(config, tracker=tracker, progress=SilentProgress())
    except StopRequested as stopped:
        return CellOutcome(cell, "stopped", tracker.run_id, stop_reason=str(stopped), resumed=job.resume_run_id is not None)
    except Exception as exc:
        error = f"{type(exc).__name__}: {exc}".splitlines()[0][:500]
        if tracker.run_id is not None:
            _attach_error(tracker, error, traceback.format_exc())
        return CellOutcome(cell, "failed", tracker.run_id, error=error)
    return CellOutcome(
        cell, "finished", result.run_id, solved=result.solved,
        interaction_time_to_success=result.interaction_time_to_success,
        interaction_seconds=result.interaction_seconds, wall_seconds=result.wall_seconds,
        stop_reason=result.stop_reason, resumed=resumed,
    )


def _attach_error(tracker, error: str, trace: str) -> None:
    """The error line as a tag and the traceback as ``error.txt`` (best effort)."""
    try:
        tracker.set_tags({ERROR_TAG: error})
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "error.txt")
            with open(path, "w") as fh:
                fh.write(trace)
            tracker.client.log_artifact(tracker.run_id, path)
    except Exception:  # the run is already marked FAILED by the runner; the outcome carries the error
        pass


# ---------------------------------------------------------------------------------------------
# executors: submit / wait / result over a bounded number of cells in flight
# ---------------------------------------------------------------------------------------------


class _Pool(Protocol):
    def submit(self, job: CellJob) -> Any: ...

    def wait(self, handles: Sequence[Any], timeout: float) -> list[Any]: ...

    def result(self, handle: Any) -> CellOutcome: ...

    def request_stop(self) -> None: ...

    def close(self, cancel: bool) -> None: ...


class WorkerProcessDied(RuntimeError):
    """A cell's process ended (crash, out of memory, killed) without handing back its outcome."""


def _cell_process_main(job: CellJob, conn) -> None:
    """Body of a local cell process: run the cell, send ``("outcome", CellOutcome)`` or
    ``("error", exception)`` back; a stop request (SIGTERM, as ``KeyboardInterrupt``) ends it quietly
    after the runner has marked the run KILLED."""
    try:
        message = ("outcome", run_cell(job))
    except KeyboardInterrupt:
        return
    except Exception as exc:  # not a learner failure (run_cell records those): hand it to the driver
        message = ("error", exc)
    conn.send(message)
    conn.close()


class _CellProcess:
    """One cell in its own spawned process, its outcome coming back over a one-way pipe."""

    def __init__(self, context, job: CellJob) -> None:
        self.reader, writer = context.Pipe(duplex=False)
        self.process = context.Process(target=_cell_process_main, args=(job, writer), name=f"cell-{job.cell.seed}")
        self.process.start()
        writer.close()  # the child holds the only writer: its end is EOF here

    def outcome(self) -> CellOutcome:
        try:
            kind, value = self.reader.recv() if self.reader.poll() else (None, None)
        except EOFError:
            kind, value = None, None
        self.process.join()
        self.reader.close()
        if kind == "outcome":
            return value
        if kind == "error":
            raise value
        raise WorkerProcessDied(f"the cell's process exited with code {self.process.exitcode} before handing back its outcome")


class LocalPool:
    """One spawned process per cell (fresh interpreter state, no pool machinery to break): at most
    ``workers`` run at once, bounded by the sweep driver."""

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self.workers = workers
        self._context = multiprocessing.get_context("spawn")
        self._running: list[_CellProcess] = []

    def submit(self, job: CellJob) -> _CellProcess:
        handle = _CellProcess(self._context, job)
        self._running.append(handle)
        return handle

    def wait(self, handles, timeout):
        from multiprocessing.connection import wait

        ready = set(wait([h.reader for h in handles] + [h.process.sentinel for h in handles], timeout=timeout))
        return [h for h in handles if h.reader in ready or h.process.sentinel in ready]

    def result(self, handle: _CellProcess) -> CellOutcome:
        self._running.remove(handle)
        return handle.outcome()

    def request_stop(self) -> None:
        """Ask every running cell to stop after its trial in progress (:data:`~harness.interrupts.STOP_AFTER_TRIAL`)."""
        for handle in self._running:
            if handle.process.is_alive() and handle.process.pid is not None:
                os.kill(handle.process.pid, STOP_AFTER_TRIAL)

    def close(self, cancel: bool) -> None:
        """Stop the cells still running with SIGTERM (each marks its run KILLED, resumable), killing
        one that has not exited after :data:`WORKER_STOP_SECONDS`."""
        alive = [h.process for h in self._running if h.process.is_alive()]
        for process in alive:
            process.terminate()
        deadline = time.monotonic() + WORKER_STOP_SECONDS
        for process in alive:
            process.join(max(deadline - time.monotonic(), 0.0))
            if process.is_alive():
                process.kill()
                process.join()
        for handle in self._running:
            handle.reader.close()
        self._running = []


#: seconds a cancelled local worker gets to mark its run KILLED before it is killed
WORKER_STOP_SECONDS = 60.0


class RayPool:
    """Ray tasks (``num_cpus=1``, ``max_calls=1``) on an embedded instance or a cluster."""

    def __init__(self, workers: int | None, address: str | None) -> None:
        import logging

        import ray

        from harness.interrupts import sigterm_handler_kept

        self._ray = ray
        self._owns = not ray.is_initialized()
        self._refs: list = []
        if self._owns:
            # ray.init replaces the SIGTERM handler with its own (exit at once); an application handler
            # (the CLI's: SIGTERM takes the Ctrl-C path, runs marked KILLED) is put back afterwards
            with sigterm_handler_kept():
                if address is None:
                    os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # embedded: no token files under ~/.ray
                    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                             _temp_dir=os.path.join(tempfile.gettempdir(), f"ray-harness-{os.getuid()}"))
                else:
                    ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        self.workers = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._remote = ray.remote(num_cpus=1, max_calls=1)(run_cell)

    def submit(self, job: CellJob):
        ref = self._remote.remote(job)
        self._refs.append(ref)
        return ref

    def wait(self, handles, timeout):
        ready, _ = self._ray.wait(list(handles), num_returns=1, timeout=timeout)
        return ready

    def result(self, handle) -> CellOutcome:
        return self._ray.get(handle)

    def request_stop(self) -> None:
        """Nothing to pass on: Ray tasks cannot be signalled, so the running cells finish their runs
        (no work is lost; Ctrl-C stops them at once instead)."""

    def close(self, cancel: bool) -> None:
        """``cancel``: cancel the unfinished cells (a running one gets ``KeyboardInterrupt`` and marks
        its run KILLED, resumable) and give them :data:`WORKER_STOP_SECONDS` to do so; then stop
        the embedded instance."""
        if cancel and self._refs:
            pending = self._ray.wait(self._refs, num_returns=len(self._refs), timeout=0)[1]
            for ref in pending:
                self._ray.cancel(ref)
            if pending:
                self._ray.wait(pending, num_returns=len(pending), timeout=WORKER_STOP_SECONDS)
        self._refs = []
        if self._owns:
            self._ray.shutdown()


def check_executor(executor: str) -> None:
    """A one-line error for an unknown executor or a missing Ray (before anything starts)."""
    import importlib.util

    if executor not in ("local", "ray"):
        raise OptionError(f"--executor must be local or ray, got {executor!r}")
    if executor == "ray" and importlib.util.find_spec("ray") is None:
        raise HarnessError("the ray executor needs Ray, which is not installed: pip install 'pilco-harness[ray]'")


# ---------------------------------------------------------------------------------------------
# progress
# ---------------------------------------------------------------------------------------------


class SweepProgress(Protocol):
    def start(self, sweep_id: str, total: int, skipped: int) -> None: ...

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None: ...

    def cell_done(self, outcome: CellOutcome) -> None: ...

    def trial(self, label: str, record: dict[str, float]) -> None: ...

    def finish(self, result: SweepResult) -> None: ...


class SilentSweepProgress:
    def start(self, sweep_id: str, total: int, skipped: int) -> None:
        pass

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None:
        pass

    def cell_done(self, outcome: CellOutcome) -> None:
        pass

    def trial(self, label: str, record: dict[str, float]) -> None:
        pass

    def finish(self, result: SweepResult) -> None:
        pass


def format_duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "–"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class RichSweepProgress:
    """One bar for the whole sweep (done / running / failed, ETA) and a line per finished cell."""

    def __init__(self, console=None) -> None:
        from rich.console import Console

        self.console = console or Console(stderr=True)
        self._progress = None
        self._task = None
        self._total = 0

    def start(self, sweep_id: str, total: int, skipped: int) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._total = total
        self._progress = Progress(TextColumn(f"[bold]sweep {sweep_id}"), BarColumn(), MofNCompleteColumn(),
                                  TextColumn("{task.description}"), TimeElapsedColumn(), console=self.console, transient=True)
        self._progress.start()
        self._task = self._progress.add_task("", total=total, completed=skipped)
        if skipped:
            self.console.print(f"{skipped} of {total} cells already finished in an earlier invocation: skipped")

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None:
        if self._progress is not None:
            self._progress.update(self._task, completed=done,
                                  description=f"running {running} | failed {failed} | ETA {format_duration(eta_seconds)}")

    def cell_done(self, outcome: CellOutcome) -> None:
        style = {"failed": "red", "stopped": "yellow"}.get(outcome.status, "")
        self.console.print(outcome.line(), style=style, soft_wrap=True)

    def trial(self, label: str, record: dict[str, float]) -> None:
        from harness.progress import format_record

        self.console.print(f"{label}: {format_record(record)}", soft_wrap=True)

    def finish(self, result: SweepResult) -> None:
        if self._progress is not None:
            self._progress.stop()


# ---------------------------------------------------------------------------------------------
# the driver
# ---------------------------------------------------------------------------------------------


def _search_all(client, experiment_id: str, filter_string: str) -> list:
    runs, token = [], None
    while True:
        page = client.search_runs([experiment_id], filter_string=filter_string, max_results=1000, page_token=token)
        runs.extend(page)
        token = page.token
        if not token:
            return runs


def find_parent_run(client, experiment_id: str, sweep_id: str):
    """The parent run of ``sweep_id`` (oldest if several), or ``None``."""
    runs = _search_all(client, experiment_id, f"tags.`{SWEEP_TAG}` = '{sweep_id}' AND tags.`{ROLE_TAG}` = 'sweep'")
    return min(runs, key=lambda r: r.info.start_time) if runs else None


def child_runs(client, experiment_id: str, parent_run_id: str) -> list:
    return _search_all(client, experiment_id, f"tags.`mlflow.parentRunId` = '{parent_run_id}'")


#: seconds between two looks at the running cells' newest trials (:class:`TrialWatcher`)
TRIAL_POLL_SECONDS = 20.0


class TrialWatcher:
    """Reports each new trial of the sweep's running cells, read from the tracking store.

    Workers log every hand-over to their MLflow run; the driver already holds the store, so it
    reads the running children's newest metrics from there every :data:`TRIAL_POLL_SECONDS`
    (the same for local and Ray workers, no channel to the workers). A cell's trial number is the
    newest step of its ``interaction_seconds`` history.
    """

    def __init__(self, client, experiment_id: str, parent_run_id: str, poll_seconds: float = TRIAL_POLL_SECONDS) -> None:
        self.client, self.experiment_id, self.parent_run_id = client, experiment_id, parent_run_id
        self.poll_seconds = poll_seconds
        self._seen: dict[str, int] = {}  # run id -> newest trial reported
        self._last = -math.inf

    def poll(self, progress: SweepProgress, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if now - self._last < self.poll_seconds:
            return
        self._last = now
        try:
            running = _search_all(self.client, self.experiment_id, (
                f"tags.`mlflow.parentRunId` = '{self.parent_run_id}' AND attributes.status = 'RUNNING'"))
            for run in sorted(running, key=lambda r: r.data.tags.get("mlflow.runName", "")):
                history = self.client.get_metric_history(run.info.run_id, "interaction_seconds")
                trial = max((m.step for m in history), default=0)
                if trial <= self._seen.get(run.info.run_id, 0):
                    continue
                self._seen[run.info.run_id] = trial
                record = {**run.data.metrics, "trial": trial}
                if all(k in record for k in ("eval_success_rate", "eval_cost", "wall_seconds")):
                    progress.trial(run.data.tags.get("mlflow.runName", run.info.run_id), record)
        except Exception:  # a busy or locked store must never stop the sweep; the next poll retries
            return


def _cell_of(run) -> Cell | None:
    tags = run.data.tags
    try:
        return Cell(tags["learner"], tags["task"], int(tags["seed"]))
    except (KeyError, ValueError):
        return None


def _open_parent(client, experiment_id: str, spec: SweepSpec) -> str:
    from mlflow.entities import Param

    sweep_id = spec.sweep_id
    parent = find_parent_run(client, experiment_id, sweep_id)
    if parent is not None:
        client.update_run(parent.info.run_id, status="RUNNING")
        return parent.info.run_id
    run = client.create_run(experiment_id, run_name=f"sweep-{sweep_id}",
                            tags={SWEEP_TAG: sweep_id, ROLE_TAG: "sweep", "mlflow.runName": f"sweep-{sweep_id}"})
    canonical = spec.canonical()
    params = {
        "learners": ",".join(spec.learners),
        "tasks": ",".join(spec.tasks),
        "seeds": format_seeds(spec.seeds),
        "set": json.dumps(canonical["set"]),
        "max_trials": spec.max_trials,
        "budget_seconds": spec.budget_seconds,
        "eval_episodes": spec.eval_episodes,
        "cells": len(spec.cells()),
        "command": spec.command(),
    }
    client.log_batch(run.info.run_id, params=[Param(k, str(v)[:6000]) for k, v in params.items()])
    return run.info.run_id


def _record_failed_child(client, job: CellJob, error: str) -> str:
    """A FAILED child for a cell whose worker died before its run existed (so it is never lost)."""
    from mlflow.entities import RunTag

    cell = job.cell
    run = client.create_run(job.experiment_id, run_name=cell.label, tags={
        "mlflow.parentRunId": job.parent_run_id, "mlflow.runName": cell.label, SWEEP_TAG: job.sweep_id,
        ROLE_TAG: "cell", "learner": cell.learner, "task": cell.task, "seed": str(cell.seed)})
    client.log_batch(run.info.run_id, tags=[RunTag(ERROR_TAG, error[:5000]), RunTag("stop_reason", "failed")])
    client.set_terminated(run.info.run_id, "FAILED")
    return run.info.run_id


def _mark_crashed(client, job: CellJob, error: str) -> str:
    """The child a dead worker left RUNNING is marked KILLED with the error (the next invocation
    continues it from its last checkpoint); without one, a FAILED child records the error."""
    from mlflow.entities import RunTag

    run_id = _running_child(client, job)
    if run_id is None:
        return _record_failed_child(client, job, error)
    client.log_batch(run_id, tags=[RunTag(ERROR_TAG, error[:5000])])
    client.set_terminated(run_id, "KILLED")
    return run_id


def _running_child(client, job: CellJob) -> str | None:
    """The newest child run of ``job``'s cell still marked RUNNING, if any."""
    cell = job.cell
    running = _search_all(client, job.experiment_id, (
        f"tags.`mlflow.parentRunId` = '{job.parent_run_id}' AND tags.learner = '{cell.learner}' AND tags.task = '{cell.task}' "
        f"AND tags.seed = '{cell.seed}' AND attributes.status = 'RUNNING'"))
    return max(running, key=lambda r: r.info.start_time).info.run_id if running else None


def run_sweep(
    spec: SweepSpec,
    tracking_uri: str | None = None,
    executor: Executor = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: SweepProgress | None = None,
) -> SweepResult:
    """Run (or resume) ``spec`` and return every cell's outcome; failed cells do not raise.

    ``kill -USR1`` to this process (on its main thread) drains the sweep: no more cells start,
    running local cells stop after their trial in progress (``stopped`` outcomes; Ray cells run
    to their end), and the result comes back with :attr:`SweepResult.stopped_early`, the parent
    run KILLED; the same spec run again continues.

    Everything the user can get wrong (plugins, options, limits, executor) is checked before the
    store is touched. ``workers`` defaults to :func:`default_workers` (local) or to the Ray
    cluster's CPUs (``--address``) / :func:`default_workers` (embedded Ray).
    """
    from harness.tracking import ensure_experiment, open_client, resolve_tracking_uri

    check_executor(executor)
    if workers is not None and workers < 1:
        raise OptionError(f"--workers must be >= 1, got {workers}")
    if address is not None and executor != "ray":
        raise OptionError("--address is for --executor ray")
    setups = validate(spec)
    progress = progress or SilentSweepProgress()

    uri = resolve_tracking_uri(tracking_uri)
    client = open_client(uri)
    experiment_id = ensure_experiment(client, SWEEP_EXPERIMENT, uri)
    sweep_id = spec.sweep_id
    parent_run_id = _open_parent(client, experiment_id, spec)

    finished: dict[Cell, str] = {}
    newest: dict[Cell, Any] = {}
    for run in child_runs(client, experiment_id, parent_run_id):
        cell = _cell_of(run)
        if cell is None:
            continue
        if run.info.status == "FINISHED":
            finished[cell] = run.info.run_id
        if cell not in newest or run.info.start_time > newest[cell].info.start_time:
            newest[cell] = run
    interrupted = {c: r.info.run_id for c, r in newest.items() if r.info.status in ("KILLED", "RUNNING")}
    outcomes = [CellOutcome(c, "skipped", finished[c]) for c in spec.cells() if c in finished]
    jobs = deque(
        CellJob(c, setups[(c.learner, c.task)]["learner_options"], setups[(c.learner, c.task)]["task_options"],
                spec.max_trials, spec.budget_seconds, spec.eval_episodes, uri, experiment_id, parent_run_id, sweep_id,
                setups[(c.learner, c.task)]["extra_params"], interrupted.get(c))
        for c in spec.cells() if c not in finished
    )
    result = SweepResult(sweep_id, parent_run_id, experiment_id, uri, outcomes)
    total = len(spec.cells())
    status = "FAILED"  # unless the loop completes; KILLED on Ctrl-C
    pool: _Pool | None = None
    stop = StopRequests.listen()  # kill -USR1: no new cells, the running ones stop after their trial
    try:
        if jobs:
            if executor == "ray":
                pool = RayPool(workers or (None if address else default_workers()), address)
            else:
                pool = LocalPool(workers or default_workers())
        progress.start(sweep_id, total, len(outcomes))
        if pool is not None:
            _drive(pool, jobs, pool.workers, result, client, progress, TrialWatcher(client, experiment_id, parent_run_id), stop)
        result.not_started = len(jobs)  # > 0 only after a stop request
        status = "KILLED" if result.stopped_early else "FINISHED" if not result.failed else "FAILED"
    except KeyboardInterrupt:
        status = "KILLED"
        raise
    finally:
        stop.restore()
        if pool is not None:
            pool.close(cancel=status != "FINISHED")
        progress.finish(result)
        _close_parent(client, parent_run_id, result, total, executor, status)
    return result


def _drive(pool: _Pool, jobs: deque, workers: int, result: SweepResult, client, progress: SweepProgress,
           watcher: TrialWatcher | None = None, stop: StopRequests | None = None) -> None:
    """Run ``jobs`` with at most ``workers`` in flight. Once ``stop`` is set (a stop request), no
    more cells start and the running ones are asked to stop after their trial in progress; it
    returns when they have, leaving the cells not started in ``jobs``."""
    inflight: dict[Any, tuple[CellJob, float]] = {}
    durations: list[float] = []
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
                inflight[pool.submit(job)] = (job, time.perf_counter())
            report()
            if watcher is not None:
                watcher.poll(progress)
            for handle in pool.wait(list(inflight), timeout=1.0):
                job, t0 = inflight.pop(handle)
                try:
                    outcome = pool.result(handle)
                except Exception as exc:  # the worker process itself died (crash, out of memory, killed)
                    cause = str(exc) if isinstance(exc, WorkerProcessDied) else f"{type(exc).__name__}: {exc}"
                    error = f"worker process died ({cause}); re-run the sweep to retry".splitlines()[0]
                    outcome = CellOutcome(job.cell, "failed", _mark_crashed(client, job, error), error=error)
                if outcome.status == "failed" and outcome.run_id is None:
                    outcome.run_id = _record_failed_child(client, job, outcome.error)
                durations.append(time.perf_counter() - t0)
                result.outcomes.append(outcome)
                progress.cell_done(outcome)
    except KeyboardInterrupt:
        # stop the running cells (each normally marks its run KILLED itself); a cell stopped before it
        # could (a force-killed process, a Ray task whose result came back cancelled first) is marked here
        pool.close(cancel=True)
        for job, _ in inflight.values():
            run_id = _running_child(client, job)
            if run_id is not None:
                client.set_terminated(run_id, "KILLED")
        raise
    report()


def _close_parent(client, parent_run_id: str, result: SweepResult, total: int, executor: str, status: str) -> None:
    from mlflow.entities import RunTag

    counts = {s: len(result.with_status(s)) for s in ("finished", "failed", "skipped", "stopped")}
    try:
        client.log_batch(parent_run_id, tags=[
            RunTag("harness.cells_total", str(total)),
            RunTag("harness.cells_finished", str(counts["finished"] + counts["skipped"])),
            RunTag("harness.cells_failed", str(counts["failed"])),
            RunTag("harness.cells_stopped", str(counts["stopped"])),
            RunTag("harness.last_executor", executor),
        ])
    finally:
        client.set_terminated(parent_run_id, status)

