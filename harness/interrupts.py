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


def _raise_interrupt(signum: int, frame) -> None:
    raise KeyboardInterrupt(f"terminated by signal {signum}")


def terminate_as_interrupt() -> bool:
    """Make SIGTERM raise ``KeyboardInterrupt`` in this process; returns whether it was installed
    (signal handlers can only be set from the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    signal.signal(signal.SIGTERM, _raise_interrupt)
    return True
