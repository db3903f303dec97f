"""SIGTERM handled like Ctrl-C.

``kill PID``, batch schedulers (SLURM's time limit) and container runtimes stop a process with
SIGTERM. By default it ends Python at once, leaving the run RUNNING in the tracking store with no
word on how to continue. :func:`terminate_as_interrupt` makes SIGTERM raise ``KeyboardInterrupt``
instead, so it takes the Ctrl-C path: the runner marks the run KILLED (its last per-trial
checkpoint stays), the CLI prints the ``--resume`` command, a sweep driver stops its workers and
marks its parent run KILLED. (A job started in the background by a non-interactive shell ignores
SIGINT, so for it SIGTERM is the way to stop it cleanly.)
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


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
