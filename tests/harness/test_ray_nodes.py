"""A Ray node dies mid-sweep: its cell runs again on the other node and resumes its run from the
last checkpoint stored on the tracking server (no shared file system), and the sweep's results are
those of an uninterrupted local sweep, down to `harness report`'s tables (but wall times and run ids).
A worker that lives on after its node is lost (a node cut off) is the lease tests' case
(`tests/harness/test_sweep_lease.py`): here the whole node dies, its workers with it.

A head (no CPUs) and two one-CPU worker nodes, each with its own temp folder and working folder,
run PILCO cells against `harness store serve`; once a cell has a checkpoint in the store, its node
is killed (SIGKILL to its daemons and to its workers, which run in process groups of their own). Skipped (visibly) without Ray's ``ray`` command or
PostgreSQL's binaries. Every process started is killed whatever the test's end.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from harness.store import Store, layout
from harness.store.server import postgres_available
from harness.sweep import SweepSpec
from tests.harness.served_store import free_port, free_ports, serving, store_dir  # noqa: F401 (fixtures)
from tests.processes import HarnessProcess, run_harness

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(importlib.util.find_spec("ray") is None or shutil.which("ray") is None, reason="Ray (and its ray command) not installed"),
    pytest.mark.skipif(not postgres_available(), reason="PostgreSQL binaries (initdb, pg_ctl, postgres) not on PATH"),
]

REPO = Path(__file__).resolve().parents[2]
TRIALS = 5
#: PILCO small enough for a few seconds a trial on one core
SETTINGS = ["--set", "num_centres=3", "--set", "policy_max_evaluations=3", "--set", "gp_max_evals=10", "--set", "horizon=10"]
SWEEP = ["sweep", "--learners", "pilco", "--tasks", "cartpole", "--seeds", "0-1", "--max-trials", str(TRIALS),
         "--eval-episodes", "1", *SETTINGS, "--quiet"]
SPEC = SweepSpec(("pilco",), ("cartpole",), (0, 1), max_trials=TRIALS, eval_episodes=1,
                 assignments=(("num_centres", "3"), ("policy_max_evaluations", "3"), ("gp_max_evals", "10"), ("horizon", "10")))


class RayNode:
    """``ray start`` in its own session: the node's daemons and workers share its process group."""

    def __init__(self, root: Path, name: str, args: list[str]) -> None:
        self.temp_dir = Path(f"/tmp/raynodes-{os.getpid()}-{name}")  # short: Ray's socket paths have a length limit
        cwd = root / name
        cwd.mkdir(parents=True)
        ports = free_ports(8)
        port_args = ["--node-manager-port", ports[0], "--object-manager-port", ports[1], "--dashboard-agent-listen-port", ports[2],
                     "--dashboard-agent-grpc-port", ports[3], "--runtime-env-agent-port", ports[4], "--metrics-export-port", ports[5]]
        workers = free_ports(16)
        command = ["ray", "start", *args, "--temp-dir", str(self.temp_dir), *map(str, port_args),
                   "--min-worker-port", str(workers[0]), "--max-worker-port", str(workers[-1]), "--disable-usage-stats"]
        env = {**os.environ, "RAY_AUTH_MODE": "disabled", "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        self.log = cwd / "ray-start.log"
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(command, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        assert self.proc.wait(timeout=120) == 0, self.log.read_text()

    def runs(self, node_id: str) -> bool:
        """Whether this is the node ``node_id`` (Ray names its port files after it)."""
        return any(node_id in p.name for p in (self.temp_dir / "session_latest").iterdir())

    def kill(self) -> None:
        """SIGKILL to the node's daemons (its process group) and to the workers they started: Ray's
        workers run in process groups of their own, and one left alive goes on with its cell until it
        notices its raylet is gone, which can be after the cell's last trial (the driver then finds
        the cell's run finished, :func:`harness.sweep.driver._retry_lost`, and nothing is resumed)."""
        for pid in self._processes():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def _processes(self) -> list[int]:
        """The node's processes: those in its session (``ray start`` began one; the workers' own process
        groups stay in it) or its process group and, transitively, their children."""
        parents: dict[int, int] = {}
        groups: dict[int, tuple[int, int]] = {}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(entry.name)], groups[int(entry.name)] = int(fields[1]), (int(fields[2]), int(fields[3]))
        found = {pid for pid, (group, session) in groups.items() if self.proc.pid in (group, session)}
        while True:
            more = {pid for pid, parent in parents.items() if parent in found} - found
            if not more:
                return sorted(found)
            found |= more

    def remove(self) -> None:
        self.kill()
        shutil.rmtree(self.temp_dir, ignore_errors=True)


def deterministic_histories(store: Store, run_id: str) -> dict[str, list[tuple[int, float]]]:
    """Every metric's (step, value) history but the wall-clock ones."""
    keys = [k for k in store.run(run_id).metrics if "seconds" not in k or k.startswith("interaction")]
    return {k: sorted((m.step, m.value) for m in store.client.get_metric_history(run_id, k)) for k in keys}



def same_columns(path: Path) -> list[dict[str, str]]:
    """A report's CSV rows without the columns that differ between two stores of the same results
    (wall-clock times, run ids)."""
    import csv

    with open(path) as fh:
        return [{k: v for k, v in row.items() if "wall" not in k and not k.startswith("run_id")} for row in csv.DictReader(fh)]


def cell_runs(store: Store, parent_id: str, experiment_id: str) -> dict[int, list]:
    found: dict[int, list] = {}
    for run in store.children(parent_id, experiment_id):
        found.setdefault(int(run.tags["seed"]), []).append(run)
    return found


def test_a_cell_whose_node_dies_resumes_on_another_node_from_its_stored_checkpoint(serving, tmp_path):
    _, uri, _ = serving
    local = tmp_path / "local"
    local.mkdir()
    code, output = run_harness([*SWEEP, "--workers", "2", "--tracking-uri", f"sqlite:///{local}/mlflow.db"], local, timeout=600)
    assert code == 0, output
    baseline = Store(f"sqlite:///{local}/mlflow.db")
    (base_parent,) = baseline.sweep_parents(SPEC.sweep_id, baseline.experiment_id("cartpole"))
    expected = {seed: deterministic_histories(baseline, run.run_id)
                for seed, (run,) in cell_runs(baseline, base_parent.run_id, base_parent.experiment_id).items()}
    assert sorted(expected) == [0, 1]

    nodes: list[RayNode] = []
    try:
        head_port = free_port()
        nodes.append(RayNode(tmp_path, "head", ["--head", "--num-cpus", "0", "--port", str(head_port), "--include-dashboard", "false",
                                                "--dashboard-port", str(free_port())]))
        address = f"127.0.0.1:{head_port}"
        workers = [RayNode(tmp_path, f"w{i}", ["--address", address, "--num-cpus", "1"]) for i in (1, 2)]
        nodes += workers
        store = Store(uri)
        with HarnessProcess([*SWEEP, "--executor", "ray", "--address", address, "--tracking-uri", uri], tmp_path,
                            env={"RAY_AUTH_MODE": "disabled"}) as proc:
            victim = None
            deadline = time.monotonic() + 300
            while victim is None:
                assert time.monotonic() < deadline and proc.proc.poll() is None, proc.output()
                time.sleep(0.5)
                experiment_id = store.experiment_id("cartpole")
                parents = store.sweep_parents(SPEC.sweep_id, experiment_id) if experiment_id else []
                for run in (store.children(parents[0].run_id, experiment_id) if parents else []):
                    trials = len(run.history(layout.INTERACTION_SECONDS))
                    node_id = run.tags.get(layout.NODE_TAG)
                    if (run.status == "RUNNING" and node_id and 1 <= trials <= TRIALS - 3
                            and store.client.list_artifacts(run.run_id, "checkpoints")):
                        victim = (run, trials, next(w for w in workers if w.runs(node_id)))
                        victim[2].kill()
                        break
            code = proc.wait(timeout=480)
            output = proc.output()
        assert code == 0, output
        run, trials_at_kill, node = victim
        assert f"worker lost on node {run.tags[layout.NODE_TAG]}" in output, output

        (parent,) = store.sweep_parents(SPEC.sweep_id, experiment_id)
        assert parent.status == "FINISHED" and parent.tags["harness.cells_retried"] == "1" and parent.metrics["cells_retried"] == 1
        assert f"resumed run {run.run_id} after trial" in parent.tags["harness.cell_retries"]
        by_seed = cell_runs(store, parent.run_id, experiment_id)
        assert sorted(by_seed) == [0, 1] and all(len(runs) == 1 and runs[0].status == "FINISHED" for runs in by_seed.values())
        resumed = store.run(run.run_id)  # the same run, continued
        resumed_at = [int(k.rsplit("_", 1)[1]) for k in resumed.tags if k.startswith("git_sha.resumed_at_trial_")]
        assert len(resumed_at) == 1 and resumed_at[0] > 1, resumed.tags
        assert resumed.tags[layout.NODE_TAG] != run.tags[layout.NODE_TAG]  # it ended on the other node
        for seed, histories in expected.items():
            got = deterministic_histories(store, by_seed[seed][0].run_id)
            assert [s for s, _ in got[layout.INTERACTION_SECONDS]] == list(range(1, TRIALS + 1))  # one value a trial
            assert got == histories, f"seed {seed}"
        # the report against the server gives the tables of the uninterrupted local sweep (but wall times and run ids)
        tables = {}
        for name, store_uri in (("server", uri), ("local", f"sqlite:///{local}/mlflow.db")):
            code, output = run_harness(["report", "--tracking-uri", store_uri, "--sweep", SPEC.sweep_id, "--out", str(tmp_path / name),
                                        "--no-publish"], tmp_path, timeout=300)
            assert code == 0, output
            tables[name] = {f: same_columns(tmp_path / name / f) for f in ("comparison_cartpole.csv", "runs_cartpole.csv")}
        assert len(tables["local"]["runs_cartpole.csv"]) == 2 and len(tables["local"]["comparison_cartpole.csv"]) == 1
        assert tables["server"] == tables["local"]
        print(json.dumps({"killed_at_trial": trials_at_kill, "resumed_at_trial": resumed_at[0]}))
    finally:
        for node in reversed(nodes):
            node.remove()
