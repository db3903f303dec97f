"""`harness store serve`: MLflow on PostgreSQL with its artifacts served, a bench run written to it and
read back through the server alone, a clean stop on SIGTERM, and the errors when PostgreSQL stops.

Skipped (visibly) where PostgreSQL's binaries are not on PATH. As root, PostgreSQL runs as the user
``postgres``, so the store's folder is made in the system temp folder, traversable by every user.
"""

from __future__ import annotations

import signal
import socket

import pytest
from click.testing import CliRunner

from harness.cli import main
from harness.errors import TrackingError
from harness.store.server import postgres_available, postgres_running, stop_postgres
from tests.harness.served_store import serving, store_dir  # noqa: F401 (fixtures)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not postgres_available(), reason="PostgreSQL binaries (initdb, pg_ctl, postgres) not on PATH"),
]


def test_a_bench_run_on_the_served_store_reads_back_through_the_server_and_sigterm_stops_both(serving, tmp_path, monkeypatch):
    proc, uri, paths = serving
    assert f"--executor ray --tracking-uri {uri}" in proc.output()
    monkeypatch.chdir(tmp_path)  # no local store beside the test: everything goes through the server
    bench = CliRunner().invoke(main, ["bench", "--learner", "random", "--task", "cartpole", "--seed", "0", "--max-trials", "2",
                                      "--eval-episodes", "1", "-q", "--tracking-uri", uri])
    assert bench.exit_code == 0, bench.output
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "mlruns").exists()

    from harness.report.loading import load
    from harness.store import Store

    store = Store(uri)
    data = load(store, include_bench=True)
    [record] = data.runs
    assert (record.learner, record.task, record.seed, record.status) == ("random", "cartpole", 0, "FINISHED")
    run = record.reader
    assert run.local_root is None  # no shared path: the files come through the server
    assert set(run.history("interaction_seconds")) == {1, 2}
    assert run.metric("interaction_seconds_total") == record.interaction_seconds > 0
    assert {"result.json", "episodes/interaction_episodes.npz"} <= {a.path for a in run.all_artifacts()}
    import json

    assert json.loads(run.file("result.json").read_text())["run_id"] == record.run_id
    assert len(run.episodes()) >= 2
    run.close()
    assert any(paths.artifacts.rglob("result.json"))  # the server keeps them in the store's folder

    proc.signal(signal.SIGTERM)
    assert proc.wait(timeout=90) == 0, proc.output()
    assert "stopped; the store is kept" in proc.output()
    assert not postgres_running(paths)
    with pytest.raises(TrackingError, match="does not answer"):
        Store(uri)


def test_postgresql_stopped_under_the_server_ends_it_with_one_line_naming_the_store_and_the_fix(serving):
    proc, uri, paths = serving
    stop_postgres(paths)
    assert proc.wait(timeout=90) == 2, proc.output()
    last = proc.output().strip().splitlines()[-1]
    assert last.startswith(f"error: PostgreSQL of the store {paths.directory} stopped") and "harness store serve --dir" in last, last
    failed = CliRunner().invoke(main, ["bench", "-l", "random", "-t", "cartpole", "--max-trials", "1", "-q", "--tracking-uri", uri])
    assert failed.exit_code == 2 and f"the tracking server {uri} does not answer" in failed.output, failed.output


def test_the_serve_errors_name_the_problem_and_the_fix(tmp_path, monkeypatch):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = CliRunner().invoke(main, ["store", "serve", "--dir", str(tmp_path / "s"), "--port", str(port)])
        assert result.exit_code == 2 and f"port {port} on 127.0.0.1 (the MLflow server) is busy; pass another with --port" in result.output
    monkeypatch.setenv("PATH", str(tmp_path))  # no PostgreSQL binaries
    result = CliRunner().invoke(main, ["store", "serve", "--dir", str(tmp_path / "s")])
    assert result.exit_code == 2 and "PostgreSQL's initdb is not on PATH; install PostgreSQL" in result.output, result.output


def test_a_run_outlives_a_restart_of_the_tracking_server(store_dir, tmp_path):  # noqa: F811 (fixture)
    """The tracking server stopped (SIGTERM: MLflow and PostgreSQL) and started again on the same store
    while a PILCO run writes to it: the run's writes wait with MLflow's back-off and the run finishes,
    every trial logged once, in the same run."""
    from tests.harness.served_store import ServedStore
    from tests.processes import HarnessProcess

    served = ServedStore(store_dir, tmp_path)
    bench = None
    try:
        served.start()
        bench = HarnessProcess(["bench", "--learner", "pilco", "--task", "cartpole", "--seed", "0", "--max-trials", "4",
                                "--eval-episodes", "1", "--set", "learner.num_centres=3", "--set", "learner.policy_max_evaluations=3",
                                "--set", "learner.gp_max_evals=10", "--set", "learner.plots=false", "--set", "task.horizon=10",
                                "--tracking-uri", served.uri], tmp_path)
        bench.wait_for("trial 1/4", timeout=240)
        assert served.stop() == 0, served.proc.output()
        assert bench.proc.poll() is None and "trial 4/4" not in bench.output()  # the outage falls inside the run
        served.start()
        assert bench.wait(timeout=600) == 0, bench.output()
    finally:
        if bench is not None and bench.proc.poll() is None:
            bench.stop()
        served.stop()
    assert "trial 4/4" in bench.output()

    from harness.report.loading import load
    from harness.store import Store

    served.start()  # read the run back from the restarted store
    try:
        [record] = load(Store(served.uri), include_bench=True).runs
        assert record.status == "FINISHED" and record.reader.history("interaction_seconds") == {1: 1.0, 2: 2.0, 3: 3.0, 4: 4.0}
        record.reader.close()
    finally:
        served.stop()
