"""Cell leases (:mod:`harness.sweep.lease`): a worker the driver took for lost, but which lives on,
writes nothing once its cell has been given to another worker; the cell's run is resumed once and
every trial is logged once.

The lost worker is a thread of this process (the driver is the real one; only the pool is a
stand-in): it holds its run at the third trial until the sweep has finished, then tries to go on.
"""

from __future__ import annotations

import sys
import threading
from concurrent.futures import Future

import pytest

from harness.store import Store, layout
from harness.sweep import SweepSpec, pools, run_sweep
from harness.sweep.cell import CellJob, run_cell
from harness.sweep.lease import LeaseLost, grant, lease_tag, revoke
from harness.sweep.spec import Cell
from tests.harness.sweep_site import children_by_cell, plugin_paths, plugins  # noqa: F401 (fixtures)

TRIALS = 5


class NodeLost(RuntimeError):
    pass


class LosingPool:
    """A pool whose first submission's handle is ``"lost"``: :meth:`result` reports its worker lost;
    later submissions run inline. Subclasses define ``first(job)``: what the first submission does."""

    workers = 1
    fence_grace = 0.0

    def __init__(self) -> None:
        self.submitted: list[CellJob] = []

    def submit(self, job):
        self.submitted.append(job)
        if len(self.submitted) == 1:
            self.first(job)
            return "lost"
        future = Future()
        future.set_result(run_cell(job))
        return future

    def wait(self, handles, timeout):
        return list(handles)

    def result(self, handle):
        if handle == "lost":
            raise NodeLost("its node died")
        return handle.result()

    def lost(self, exc) -> bool:
        return isinstance(exc, NodeLost)

    def request_stop(self) -> None:
        pass

    def close(self, cancel: bool) -> None:
        pass


class CutOffPool(LosingPool):
    """The first submission runs in a thread that the pool then reports lost (its node "died"
    once the run has stored two trials); later submissions run inline. The cut-off thread lives on.
    ``left_as="KILLED"``: before the loss is reported, the run is marked KILLED, as a worker does that
    takes its raylet's end for an interrupt."""

    fence_grace = 0.2

    def __init__(self, left_as: str = "RUNNING") -> None:
        super().__init__()
        self.cut_off: dict = {}
        self.left_as = left_as

    def first(self, job: CellJob) -> None:
        def body():
            self.cut_off["outcome"] = run_cell(job)

        self.cut_off["thread"] = threading.Thread(target=body, daemon=True)
        self.cut_off["thread"].start()

    def wait(self, handles, timeout):
        if "lost" in handles:
            gated = sys.modules["sweep_test_plugins"].Gated
            assert gated.WAITING.wait(120), "the first worker never reached its third trial"
            if self.left_as != "RUNNING":
                job = self.submitted[0]
                store = Store(job.tracking_uri)
                (run,) = store.children(job.parent_run_id, job.experiment_id)
                store.set_status(run.run_id, self.left_as)
        return list(handles)


@pytest.mark.parametrize("left_as, seed", [("RUNNING", 5), ("KILLED", 6)])
def test_a_lost_worker_that_lives_on_writes_nothing_and_its_cell_resumes_once(plugins, mlflow_uri, monkeypatch, left_as, seed):
    gated = sys.modules.get("sweep_test_plugins")
    if gated is not None:  # a fresh gate for each case (the store is the session's: a seed of its own each)
        gated.Gated.WAITING.clear()
        gated.Gated.GATE.clear()
    pool = CutOffPool(left_as)
    monkeypatch.setattr(pools, "make_pool", lambda *args: pool)
    spec = SweepSpec(("sweep-gated",), ("sweep-toy",), (seed,), max_trials=TRIALS, eval_episodes=1)
    try:
        result = run_sweep(spec, mlflow_uri)
    finally:
        sys.modules["sweep_test_plugins"].Gated.GATE.set()  # the cut-off worker goes on: its third trial, then its writes
    pool.cut_off["thread"].join(60)
    assert not pool.cut_off["thread"].is_alive()

    (outcome,) = result.outcomes
    assert outcome.status == "finished" and outcome.resumed
    (retry,) = result.retries
    assert retry.run_id == outcome.run_id and retry.trials == 2
    stale = pool.cut_off["outcome"]
    assert stale.status == "superseded" and stale.run_id == outcome.run_id
    assert "not allowed to" in stale.error and "gave this cell to another worker" in stale.error

    (run,) = children_by_cell(mlflow_uri, result)[("sweep-gated", seed)]
    assert run.status == "FINISHED" and run.tags[layout.STOP_REASON_TAG] == "max trials"
    assert "git_sha.resumed_at_trial_3" in run.tags
    steps = [m.step for m in run.store.client.get_metric_history(run.run_id, layout.INTERACTION_SECONDS)]
    assert sorted(steps) == list(range(1, TRIALS + 1))  # every trial once: none from the cut-off worker
    assert run.history(layout.INTERACTION_SECONDS) == {t: 4.0 * t for t in range(1, TRIALS + 1)}
    # each submission held its own lease; the one on the parent now is the last one's
    first, second = (job.lease for job in pool.submitted)
    assert first and second and first != second
    parent = Store(mlflow_uri).run(next(iter(result.parents.values()))[1])
    assert parent.tags[lease_tag(Cell("sweep-gated", "sweep-toy", seed))] == second


class FinishedThenLostPool(LosingPool):
    """The first submission runs to its end inline, and then the pool reports its worker lost (a
    worker that lived on after its node was killed, and finished its run before the driver heard
    of the node's death)."""

    def first(self, job: CellJob) -> None:
        assert run_cell(job).status == "finished"


def test_a_cell_whose_lost_worker_had_finished_its_run_is_finished_not_run_again(plugins, mlflow_uri, monkeypatch):
    pool = FinishedThenLostPool()
    monkeypatch.setattr(pools, "make_pool", lambda *args: pool)
    spec = SweepSpec(("sweep-steps",), ("sweep-toy",), (3,), max_trials=2, eval_episodes=1)
    result = run_sweep(spec, mlflow_uri)
    assert len(pool.submitted) == 1 and result.retries == []
    (outcome,) = result.outcomes
    (run,) = children_by_cell(mlflow_uri, result)[("sweep-steps", 3)]
    assert run.status == "FINISHED" and outcome.run_id == run.run_id
    # seed 3 of sweep-steps solves after 8 s (tests.harness.sweep_site.EXPECTED_STEPS), read back from the run
    assert (outcome.status, outcome.solved, outcome.interaction_time_to_success, outcome.interaction_seconds) == ("finished", True, 8.0, 8.0)
    assert outcome.stop_reason == run.tags[layout.STOP_REASON_TAG] and outcome.wall_seconds > 0
    parent = Store(mlflow_uri).run(next(iter(result.parents.values()))[1])
    assert parent.status == "FINISHED" and parent.tags["harness.cells_retried"] == "0"


def test_a_worker_whose_lease_was_revoked_before_it_started_creates_no_run(plugins, mlflow_uri):
    store = Store(mlflow_uri)
    experiment_id = store.ensure_experiment("sweep-toy")
    parent_id = store.create_run(experiment_id, "parent", {layout.ROLE_TAG: layout.ROLE_SWEEP})
    cell = Cell("sweep-steps", "sweep-toy", 2)
    token = grant(store, parent_id, cell)
    revoke(store, parent_id, cell)  # the driver gave up on this submission before its worker started
    job = CellJob(cell, {}, {}, 2, None, 1, store.uri, experiment_id, parent_id, "lease-test", lease=token)
    outcome = run_cell(job)
    assert outcome.status == "superseded" and outcome.run_id is None
    assert "not allowed to start its run" in outcome.error
    assert store.children(parent_id, experiment_id) == []
    assert outcome.line().startswith("sweep-steps-sweep-toy-s2: given to another worker (sweep-steps-sweep-toy-s2: not allowed")


def test_the_lease_check_reads_the_parent_run(mlflow_uri):
    from harness.sweep.lease import LeaseCheck

    store = Store(mlflow_uri)
    experiment_id = store.ensure_experiment("lease-check")
    parent_id = store.create_run(experiment_id, "parent", {})
    cell = Cell("a", "b", 0)

    class Holder:
        tracking_uri, client = store.uri, store.client

    token = grant(store, parent_id, cell)
    LeaseCheck(Holder(), parent_id, cell, token)("write")  # held: no error
    LeaseCheck(Holder(), parent_id, cell, None)("write")  # no lease given: nothing checked
    grant(store, parent_id, cell)
    with pytest.raises(LeaseLost, match="a-b-s0: not allowed to write"):
        LeaseCheck(Holder(), parent_id, cell, token)("write")
