"""SIGTERM handled like Ctrl-C; SIGUSR1 asks a run to stop once its trial in progress is stored.

``kill PID``, batch schedulers (SLURM's time limit) and container runtimes stop a process with
SIGTERM. By default it ends Python at once, leaving the run RUNNING in the tracking store with no
word on how to continue. :func:`terminate_as_interrupt` makes SIGTERM raise ``KeyboardInterrupt``
instead, so it takes the Ctrl-C path: the runner marks the run KILLED (its last per-trial
checkpoint stays), the CLI prints the ``--resume`` command, a sweep driver stops its workers and
marks its parent run KILLED. (A job started in the background by a non-interactive shell ignores
SIGINT, so for it SIGTERM is the way to stop it cleanly.)

SIGTERM stops a run at once: the trial in progress (for PILCO, minutes of policy search) is
redone when the run is resumed. :data:`STOP_AFTER_TRIAL` (SIGUSR1, ``kill -USR1 PID``) asks
for a stop after it instead: :class:`StopRequests` records the request, and the runner ends the
run KILLED (resumable) once that trial's records and checkpoint are stored. A sweep driver
asked this way starts no more cells and passes the request on to its running local cells.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: the signal that asks a run to stop after the trial in progress (None where the platform has no SIGUSR1)
STOP_AFTER_TRIAL: signal.Signals | None = getattr(signal, "SIGUSR1", None)


class StopRequested(KeyboardInterrupt):
    """Raised by the runner after the trial in progress when :data:`STOP_AFTER_TRIAL` asked for a
    stop; a ``KeyboardInterrupt``, so it takes the Ctrl-C path (run KILLED, resume hint)."""


def _raise_interrupt(signum: int, frame) -> None:
    raise KeyboardInterrupt(f"terminated by signal {signum}")


def _on_main_thread() -> bool:
    """Signal handlers can only be read and set from the main thread."""
    return threading.current_thread() is threading.main_thread()


def terminate_as_interrupt() -> bool:
    """Make SIGTERM raise ``KeyboardInterrupt`` in this process; returns whether it was installed
    (signal handlers can only be set from the main thread)."""
    if not _on_main_thread():
        return False
    signal.signal(signal.SIGTERM, _raise_interrupt)
    return True


@contextmanager
def held_interrupts() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then deliver the first one received to the
    handler that was in place (Ctrl-C's ``KeyboardInterrupt``, :func:`terminate_as_interrupt`'s).

    For writes that must not be cut in half: a metric batch or artifact upload to the tracking
    store (an interrupt inside SQLAlchemy leaves a logged traceback and a rolled-back session), a
    checkpoint. Off the main thread (where handlers cannot be set) the block runs unprotected.
    """
    if not _on_main_thread():
        yield
        return
    received: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    for signum in previous:
        signal.signal(signum, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if received:
            signal.raise_signal(received[0])


@contextmanager
def sigterm_handler_kept() -> Iterator[None]:
    """Put the application's SIGTERM handler (e.g. :func:`terminate_as_interrupt`'s) back after a
    block that replaces it, such as ``ray.init`` (whose handler exits at once). Off the main
    thread, or when the handler was not set from Python, nothing is put back."""
    previous = signal.getsignal(signal.SIGTERM) if _on_main_thread() else None
    yield
    if callable(previous):
        signal.signal(signal.SIGTERM, previous)


#: a stop request that came before any :func:`stop_requests` block (see :func:`catch_stop_requests_early`)
_early_request = threading.Event()


def catch_stop_requests_early() -> None:
    """Record :data:`STOP_AFTER_TRIAL` in this process from now on, for the next
    :func:`stop_requests` block to honour. For a process started to run a run (a sweep's cell):
    the request may come while it is still importing, and the signal's default action would
    end the process."""
    if STOP_AFTER_TRIAL is not None and _on_main_thread():
        signal.signal(STOP_AFTER_TRIAL, lambda signum, frame: _early_request.set())


class StopRequests:
    """Listens for :data:`STOP_AFTER_TRIAL` from :meth:`listen` until :meth:`restore`.

    :meth:`is_set` tells whether it arrived (or arrived before, after
    :func:`catch_stop_requests_early`). :meth:`restore` puts back the handler that was in place.
    Off the main thread, or without SIGUSR1, nothing is installed and the signal keeps its
    previous meaning. :func:`stop_requests` is the same as a ``with`` block.
    """

    def __init__(self) -> None:
        self._requested = threading.Event()
        self._previous = None
        self._installed = False

    @classmethod
    def listen(cls) -> StopRequests:
        listener = cls()
        if _early_request.is_set():
            _early_request.clear()
            listener._requested.set()
        if STOP_AFTER_TRIAL is not None and _on_main_thread():
            listener._previous = signal.signal(STOP_AFTER_TRIAL, lambda signum, frame: listener._requested.set())
            listener._installed = True
        return listener

    def is_set(self) -> bool:
        return self._requested.is_set()

    def restore(self) -> None:
        if self._installed:
            signal.signal(STOP_AFTER_TRIAL, self._previous)
            self._installed = False


@contextmanager
def stop_requests() -> Iterator[StopRequests]:
    """:class:`StopRequests` listening for the duration of the block."""
    listener = StopRequests.listen()
    try:
        yield listener
    finally:
        listener.restore()
