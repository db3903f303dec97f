"""A throwaway plugin distribution for sweep/report tests, visible to spawned and Ray workers.

``install(root)`` writes ``root/site`` holding a module and a ``*.dist-info`` with entry points
(what ``pip install`` would leave, without running pip), and returns the directories to put on
``sys.path`` / ``PYTHONPATH``. Its plugins:

* task ``sweep-toy``: the harness self-test task of :mod:`tests.harness.toy` (4 s per episode);
* learner ``sweep-steps``: hands over a useless policy ``learner seed % 3`` times (one episode
  each), then the solving one; with ``--max-trials 2`` run seeds 2, 3, 4 (learner seeds
  ``derive_seeds(s)["learner"] % 3`` = 0, 1, 2) solve after 4 s, after 8 s, and not at all;
* learner ``sweep-boom``: raises ``RuntimeError("boom in the learner")`` after one episode;
* learner ``sweep-crash``: its process exits (``os._exit(3)``) after one hand-over;
* learner ``sweep-slow``: a useless hand-over every 0.2 s until stopped (for interrupting sweeps);
* learner ``sweep-gated``: resumable useless hand-overs; a run started afresh (not resumed) sets
  ``Gated.WAITING`` before its third trial and waits for ``Gated.GATE`` (a worker that lives on
  after the driver took it for lost, in one process with the driver).
"""

from __future__ import annotations

import os
from concurrent.futures import Future
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

MODULE = '''
import threading

from harness.learner import Learner
from tests.harness.toy import Proportional, ToyReach


class SweepToy(ToyReach):
    name = "sweep-toy"
    description = "toy reach for sweep tests"


class SeedSteps(Learner):
    name = "sweep-steps"
    description = "test learner: (learner seed % 3) useless hand-overs, then the solution"

    def learn(self, interaction):
        for _ in range(self.seed % 3):
            interaction.rollout(Proportional(0.0))
            yield Proportional(0.0)
        while True:
            interaction.rollout(Proportional(1.0))
            yield Proportional(1.0)


class Crash(Learner):
    name = "sweep-crash"
    description = "test learner: its process dies (os._exit) after one hand-over"

    def learn(self, interaction):
        import os

        interaction.rollout(Proportional(0.0))
        yield Proportional(0.0)
        os._exit(3)


class Slow(Learner):
    name = "sweep-slow"
    description = "test learner: a useless hand-over every 0.2 s, for as long as it is allowed"

    def learn(self, interaction):
        import time

        while True:
            interaction.rollout(Proportional(0.0))
            time.sleep(0.2)
            yield Proportional(0.0)


class Gated(Learner):
    name = "sweep-gated"
    description = "test learner: resumable; a fresh run waits before its third trial until Gated.GATE is set"
    supports_resume = True
    WAITING = threading.Event()
    GATE = threading.Event()

    def state_dict(self):
        return {"trial": self._trial}

    def learn(self, interaction):
        fresh = self._resume_state is None
        self._trial = 0 if fresh else int(self._resume_state["trial"])
        while True:
            self._trial += 1
            if fresh and self._trial == 3:
                Gated.WAITING.set()
                Gated.GATE.wait(120)
            interaction.rollout(Proportional(0.0))
            yield Proportional(0.0)


class Boom(Learner):
    name = "sweep-boom"
    description = "test learner: raises after one episode"

    def learn(self, interaction):
        interaction.rollout(Proportional(0.0))
        raise RuntimeError("boom in the learner")
        yield  # pragma: no cover
'''

ENTRY_POINTS = """[harness.learners]
sweep-steps = sweep_test_plugins:SeedSteps
sweep-boom = sweep_test_plugins:Boom
sweep-crash = sweep_test_plugins:Crash
sweep-slow = sweep_test_plugins:Slow
sweep-gated = sweep_test_plugins:Gated

[harness.tasks]
sweep-toy = sweep_test_plugins:SweepToy
"""


def install(root: Path) -> list[str]:
    site = Path(root) / "site"
    dist = site / "harness_sweep_test-0.0.0.dist-info"
    dist.mkdir(parents=True, exist_ok=True)
    (site / "sweep_test_plugins.py").write_text(MODULE)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: harness-sweep-test\nVersion: 0.0.0\n")
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    return [str(site), str(REPO)]


def activate(paths: list[str], monkeypatch) -> None:
    """Make the plugins visible here (sys.path) and in every worker process (PYTHONPATH)."""
    for path in reversed(paths):
        monkeypatch.syspath_prepend(path)
    old = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths + ([old] if old else [])))


class InlinePool:
    """Runs each cell in the calling process (``monkeypatch.setattr(pools, "LocalPool", InlinePool)``,
    ``pools`` = :mod:`harness.sweep.pools`):
    the driver and the worker function are the real ones, only the process pool is left out."""

    fence_grace = 0.0

    def __init__(self, workers: int) -> None:
        self.workers = 1

    def submit(self, job):
        from harness.sweep.cell import run_cell

        future = Future()
        future.set_result(run_cell(job))
        return future

    def wait(self, handles, timeout):
        return list(handles)

    def result(self, handle):
        return handle.result()

    def lost(self, exc) -> bool:
        return False

    def close(self, cancel: bool) -> None:
        pass


# ---- fixtures and checks shared by the sweep tests (import the fixtures into the test module) ----

@pytest.fixture(scope="module")
def plugin_paths(tmp_path_factory) -> list[str]:
    return install(tmp_path_factory.mktemp("sweep-plugins"))


@pytest.fixture
def plugins(plugin_paths, monkeypatch) -> list[str]:
    activate(plugin_paths, monkeypatch)
    return plugin_paths


#: seeds 2, 3, 4 of `sweep-steps` with --max-trials 2: solved after 4 s, solved after 8 s, unsolved at 8 s
EXPECTED_STEPS = {2: (True, 4.0), 3: (True, 8.0), 4: (False, None)}


def children_by_cell(uri: str, result) -> dict[tuple[str, int], list]:
    """The sweep's child runs (:class:`harness.store.RunReader`) by (learner, seed), over its parents."""
    from harness.store import Store

    store = Store(uri)
    out: dict[tuple[str, int], list] = {}
    for experiment_id, parent in dict.fromkeys(result.parents.values()):
        for run in store.children(parent, experiment_id):
            out.setdefault((run.tags["learner"], int(run.tags["seed"])), []).append(run)
    return out


def check_steps_cells(uri: str, result) -> None:
    """The `sweep-steps` cells of seeds 2-4 ended as EXPECTED_STEPS says, with the sweep's tags, in the task's experiment."""
    runs = children_by_cell(uri, result)
    for seed, (solved, time_to_success) in EXPECTED_STEPS.items():
        (run,) = [r for r in runs[("sweep-steps", seed)] if r.status == "FINISHED"]
        assert run.tags["solved"] == str(solved).lower()
        assert run.tags["harness.sweep_id"] == result.sweep_id and run.tags["harness.role"] == "cell"
        assert run.params["spec.state_dim"] == "1" and run.params["max_trials"] == "2"
        assert run.store.experiments()[run.experiment_id] == "sweep-toy"
        assert run.name == f"sweep-steps · sweep-toy · s{seed}"
        if solved:
            assert run.metrics["interaction_time_to_success_seconds"] == time_to_success
        else:
            assert "interaction_time_to_success_seconds" not in run.metrics
            assert run.metrics["interaction_seconds_total"] == 8.0


def sweep_runs(uri: str, spec, role: str) -> list:
    """The runs (:class:`harness.store.RunReader`) of sweep ``spec`` with ``harness.role`` ``role``
    ("sweep": its parents, "cell": their children), in any experiment."""
    from harness.store import Store

    return Store(uri).search(None, f"tags.`harness.sweep_id` = '{spec.sweep_id}' AND tags.`harness.role` = '{role}'")


def wait_until_cells_run(uri: str, spec, proc, timeout: float) -> None:
    """Return once every cell of ``spec`` has a child run past its first hand-over; fail with the
    output of ``proc`` (a :class:`tests.processes.HarnessProcess`) after ``timeout`` s."""
    import time

    deadline = time.time() + timeout
    while time.time() < deadline:
        cells = sweep_runs(uri, spec, "cell")
        if len(cells) == len(spec.cells()) and all(r.history("interaction_seconds") for r in cells):
            return
        time.sleep(0.5)
    raise AssertionError(f"the cells did not start in time:\n{proc.output()}")
