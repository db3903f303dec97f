"""Executors of a sweep's cells: a local pool of spawned processes or Ray; submit / wait / result
over a bounded number of cells in flight (the driver bounds it)."""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Sequence
from typing import Any, Literal, Protocol

from harness.errors import HarnessError, OptionError
from harness.interrupts import STOP_AFTER_TRIAL
from harness.sweep.cell import CellJob, CellOutcome, run_cell

Executor = Literal["local", "ray"]


def default_workers() -> int:
    """One cell per core, minus one core for the driver, MLflow writes and the system; at least 1.

    Cells are single-threaded; on this project's 2-core machines that is 1, so wall-clock numbers
    stay comparable with ``harness bench``. Interaction time (the benchmark's measure) is system
    time and does not depend on it.
    """
    return max(1, (os.cpu_count() or 1) - 1)


class Pool(Protocol):
    """What the driver needs of an executor (``workers``: cells it runs at a time; ``fence_grace``:
    seconds a lost cell's worker may still be finishing a write it began before its lease was
    revoked, :mod:`harness.sweep.lease`)."""

    workers: int
    fence_grace: float

    def submit(self, job: CellJob) -> Any: ...

    def wait(self, handles: Sequence[Any], timeout: float) -> list[Any]: ...

    def result(self, handle: Any) -> CellOutcome: ...

    def request_stop(self) -> None: ...

    def close(self, cancel: bool) -> None: ...

    def lost(self, exc: BaseException) -> bool:
        """Whether ``exc`` (raised by :meth:`result`) says the cell's worker was lost (its process or
        its node died): the driver runs such a cell again, resuming its run from its last checkpoint."""
        ...


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

    #: a lost local cell's process has exited (its sentinel fired): nothing of it is left to write
    fence_grace = 0.0

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

    def lost(self, exc: BaseException) -> bool:
        return isinstance(exc, WorkerProcessDied)

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

#: seconds the driver waits, after revoking the lease of a cell whose Ray worker was lost, before it
#: resumes the cell's run: a write the worker began before (one request to the store) lands first
RAY_FENCE_GRACE_SECONDS = 5.0


class RayPool:
    """Ray tasks (``num_cpus=1``, ``max_calls=1``) on an embedded instance or a cluster.

    Ray does not retry a cell itself (``max_retries=0``): its retry would start the cell afresh in a
    new run, leaving the dead worker's run RUNNING; the driver's retry resumes that run instead.
    A worker on a lost node may live on (a node cut off, a raylet killed before its workers): its
    lease is revoked and the driver waits :data:`RAY_FENCE_GRACE_SECONDS` before resuming its run.
    """

    fence_grace = RAY_FENCE_GRACE_SECONDS

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
        self._remote = ray.remote(num_cpus=1, max_calls=1, max_retries=0)(run_cell)

    def submit(self, job: CellJob):
        ref = self._remote.remote(job)
        self._refs.append(ref)
        return ref

    def wait(self, handles, timeout):
        ready, _ = self._ray.wait(list(handles), num_returns=1, timeout=timeout)
        return ready

    def result(self, handle) -> CellOutcome:
        return self._ray.get(handle)

    def lost(self, exc: BaseException) -> bool:
        from ray import exceptions

        return isinstance(exc, (exceptions.WorkerCrashedError, exceptions.NodeDiedError, exceptions.LocalRayletDiedError,
                                exceptions.ObjectLostError))

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


def make_pool(executor: str, workers: int | None, address: str | None) -> Pool:
    """The executor's pool: ``workers`` cells at a time (default: :func:`default_workers`; a Ray
    cluster given by ``address``: its CPUs)."""
    if executor == "ray":
        return RayPool(workers or (None if address else default_workers()), address)
    return LocalPool(workers or default_workers())
