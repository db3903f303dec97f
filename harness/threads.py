"""How many CPU threads a run may use, decided by the harness rather than by hand.

A ``harness bench`` run owns the machine: it may use every core it is allowed to run on, unless the
user limits it (``HARNESS_THREADS``, or ``OMP_NUM_THREADS`` as for any OpenMP program). Cells of a
sweep run side by side, one per core, so each gets one thread: the sweep's worker sets
:data:`ENV` to 1 before the learner is built (:func:`single_threaded`), and learners ask
:func:`run_threads` instead of guessing. Learners that take a ``threads`` option let a user
override the choice.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

#: environment variable holding the number of threads a run may use (set to 1 in sweep cells)
ENV = "HARNESS_THREADS"

#: the thread-count variables of the numerical libraries, set together with :data:`ENV`
LIBRARY_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_threads() -> int:
    """Threads for the run in this process: ``$HARNESS_THREADS`` if set, else a positive
    ``$OMP_NUM_THREADS`` (its first entry: the user's limit for every OpenMP library, which torch
    also follows by default), else :func:`available_cores`.

    Raises ``ValueError`` naming the variable if ``HARNESS_THREADS`` is set to something other than a
    positive integer (an ``OMP_NUM_THREADS`` the harness cannot read is left to the libraries).
    """
    value = os.environ.get(ENV)
    if value is None or value == "":
        omp = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
        return int(omp) if omp.isdigit() and int(omp) > 0 else available_cores()
    try:
        threads = int(value)
    except ValueError:
        threads = 0
    if threads < 1:
        raise ValueError(f"{ENV}={value!r} is not a positive integer (unset it to use all {available_cores()} cores)")
    return threads


def single_threaded() -> None:
    """Make this process a one-thread run (a sweep cell): :data:`ENV` and the libraries' variables
    become 1, and torch, if already imported, uses one thread."""
    os.environ[ENV] = "1"
    for var in LIBRARY_ENV:
        os.environ[var] = "1"
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """torch's intra-op threads set to ``threads`` inside the block, restored after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def stepping_threads() -> Iterator[None]:
    """One torch thread while a policy is applied one observation at a time (an episode's steps).

    Each step is a few operations on vectors of tens to hundreds of entries, too small for threads
    to pay for their start-up; a run that took every core (:func:`run_threads`) would otherwise wake
    them all at every operation. On this 2-core machine, busy with two sweep cells, a 10-episode
    double-pendulum evaluation of a 200-centre RBF policy took 5.35 s with 16 torch threads and 0.95 s
    with one. Nothing changes if torch was never imported (a learner that does not use it).
    """
    torch = sys.modules.get("torch")
    if torch is None or torch.get_num_threads() == 1:
        yield
        return
    with torch_threads(1):
        yield
