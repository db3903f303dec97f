"""`harness sweep --executor ray`: embedded Ray gives the same runs as the local pool.

Each test runs the real CLI in its own process session (:mod:`tests.processes`): Ray's driver
changes process-wide state (signal handlers, child processes that die with the thread that started
them), which must not leak into the test process, and whatever Ray leaves behind is killed with
the session.
"""

from __future__ import annotations

import signal
from types import SimpleNamespace

import pytest

from harness.sweep import SweepSpec
from tests.harness.sweep_site import check_steps_cells, plugin_paths, plugins, sweep_runs, wait_until_cells_run  # noqa: F401 (fixtures)
from tests.processes import HarnessProcess, run_harness

pytest.importorskip("ray")


def test_ray_sweep_gives_the_same_results(plugins, mlflow_uri, tmp_path):
    spec = SweepSpec(("sweep-steps", "random"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2)
    args = ["sweep", "--learners", "sweep-steps,random", "--tasks", "sweep-toy", "--seeds", "2-4", "--max-trials", "2",
            "--eval-episodes", "2", "--executor", "ray", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"]
    code, output = run_harness(args, tmp_path, timeout=600)
    assert code == 0, output
    (parent,) = sweep_runs(mlflow_uri, spec, "sweep")
    assert parent.status == "FINISHED" and parent.tags["harness.last_executor"] == "ray"
    cells = sweep_runs(mlflow_uri, spec, "cell")
    assert sorted(r.status for r in cells) == ["FINISHED"] * 6
    check_steps_cells(mlflow_uri, SimpleNamespace(sweep_id=spec.sweep_id, parents={"sweep-toy": (parent.experiment_id, parent.run_id)}))
    assert all(r.tags["solved"] == "false" for r in cells if r.tags["learner"] == "random")

    code, output = run_harness(args, tmp_path, timeout=300)  # resumes: nothing left to run, Ray not started
    assert code == 0, output
    assert f"sweep {spec.sweep_id}: 0 finished, 6 skipped" in output
    assert [r.run_id for r in sweep_runs(mlflow_uri, spec, "sweep")] == [parent.run_id]


def test_sigterm_to_a_ray_driver_cancels_the_cells_and_marks_the_runs_killed(plugins, mlflow_uri, tmp_path):
    """`kill DRIVER_PID` with --executor ray: ray.init's own SIGTERM handler (exit at once, runs left
    RUNNING) does not replace the CLI's; running cells are cancelled and mark their runs KILLED."""
    spec = SweepSpec(("sweep-slow",), ("sweep-toy",), (7, 8), max_trials=5000, eval_episodes=1)
    args = ["sweep", "--learners", "sweep-slow", "--tasks", "sweep-toy", "--seeds", "7-8", "--max-trials", "5000",
            "--eval-episodes", "1", "--executor", "ray", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"]
    with HarnessProcess(args, tmp_path) as proc:
        wait_until_cells_run(mlflow_uri, spec, proc, timeout=240)
        proc.signal(signal.SIGTERM)
        code = proc.wait(timeout=180)
        output = proc.output()
    assert code == 130, output
    assert "interrupted" in output
    assert sorted(r.status for r in sweep_runs(mlflow_uri, spec, "cell")) == ["KILLED", "KILLED"]
    assert [r.status for r in sweep_runs(mlflow_uri, spec, "sweep")] == ["KILLED"]
