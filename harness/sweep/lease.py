"""One writer per sweep cell: leases that fence off a worker the driver has given up on.

A Ray worker on a lost node (its raylet dead, or the node cut off from the head) can live on for a
while and still reach the tracking server. When the driver runs its cell again elsewhere, two
workers would write the same run: a trial logged twice, a finished run set RUNNING again. So every
submission of a cell holds a *lease*: a token the driver writes on the sweep's parent run
(tag ``harness.lease.<cell label>``) before the cell starts, and which the worker carries in its
job. Before each write to the store (creating or resuming its run, a trial's artifacts, checkpoint
and metrics, tags, the final status) the worker reads the tag; once the driver has granted the
cell to another worker (or revoked it), the tag holds another token and the worker stops with
:class:`LeaseLost`, having written nothing more.

A write whose check passed before the lease moved can still land afterwards; the driver waits
:attr:`~harness.sweep.pools.Pool.fence_grace` seconds after moving the lease before it looks at
the run again and resumes it, so such a write (one HTTP request, bounded by the tracking client's
retries) is part of what the new worker resumes from.
"""

from __future__ import annotations

import uuid
from typing import Any

from harness.errors import TrackingError
from harness.store import Store, layout
from harness.sweep.spec import Cell


class LeaseLost(TrackingError):
    """This worker's cell was handed to another worker (or given up on): it must not write again."""


def lease_tag(cell: Cell) -> str:
    """The parent run's tag that holds ``cell``'s current lease."""
    return f"{layout.LEASE_TAG_PREFIX}{cell.label}"


def grant(store: Store, parent_run_id: str, cell: Cell) -> str:
    """A new lease on ``cell`` (its token), written on the parent run: every earlier lease on the cell is void."""
    token = uuid.uuid4().hex[:16]
    store.set_tags(parent_run_id, {lease_tag(cell): token})
    return token


def revoke(store: Store, parent_run_id: str, cell: Cell) -> None:
    """Void every lease on ``cell`` (a lease nobody holds): a worker still running it writes nothing more."""
    grant(store, parent_run_id, cell)


class LeaseCheck:
    """The worker side: :meth:`__call__` raises :class:`LeaseLost` unless ``token`` is still the cell's lease.

    Args:
        tracker: what writes the cell's run (:class:`~harness.tracking.MlflowTracker`); the lease
            is read through its store (``tracking_uri``, ``client``: opened on first use).
        parent_run_id: the sweep parent run that holds the lease tag.
        cell: the cell.
        token: the lease this worker was given (``None``: no lease, nothing is checked).
    """

    def __init__(self, tracker: Any, parent_run_id: str, cell: Cell, token: str | None) -> None:
        self.tracker, self.parent_run_id, self.cell, self.token = tracker, parent_run_id, cell, token
        self._store: Store | None = None

    def __call__(self, what: str) -> None:
        if self.token is None:
            return
        if self._store is None:
            self._store = Store(self.tracker.tracking_uri, self.tracker.client)
        current = self._store.run(self.parent_run_id).tags.get(lease_tag(self.cell))
        if current != self.token:
            raise LeaseLost(f"{self.cell.label}: not allowed to {what}: the sweep driver gave this cell to another worker "
                            "(this worker was taken for lost); it stops without writing")
