"""`harness sweep --executor local`: a real process pool; failures isolated, resuming, a dying worker."""

from __future__ import annotations

from click.testing import CliRunner

from harness.cli import main
from harness.store import Store
from harness.sweep import SweepSpec, run_sweep
from tests.harness.sweep_site import (  # noqa: F401 (fixtures)
    check_steps_cells, children_by_cell, plugin_paths, plugins, sweep_runs, wait_until_cells_run)
from tests.processes import HarnessProcess


def test_local_sweep_isolates_failures_and_resumes(plugins, mlflow_uri):
    spec = SweepSpec(("sweep-steps", "sweep-boom"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2)
    result = run_sweep(spec, mlflow_uri, executor="local", workers=2)

    assert {(o.cell.learner, o.cell.seed): o.status for o in result.outcomes} == {
        **{("sweep-steps", s): "finished" for s in (2, 3, 4)}, **{("sweep-boom", s): "failed" for s in (2, 3, 4)}}
    assert all(o.error == "RuntimeError: boom in the learner" for o in result.failed)
    check_steps_cells(mlflow_uri, result)
    runs = children_by_cell(mlflow_uri, result)
    for seed in (2, 3, 4):
        (boom,) = runs[("sweep-boom", seed)]
        assert boom.status == "FAILED" and boom.tags["harness.error"] == "RuntimeError: boom in the learner"
        assert boom.tags["harness.resumable"] == "false" and boom.tags["mlflow.note.content"].startswith("**Failed** after")
    store = Store(mlflow_uri)
    (experiment_id, parent_id), = result.parents.values()
    parent = store.run(parent_id)
    assert parent.status == "FAILED" and parent.tags["harness.cells_failed"] == "3" and parent.metrics["cells_failed"] == 3
    assert parent.experiment_id == experiment_id == store.experiment_id("sweep-toy")  # the task's experiment
    assert parent.name == f"sweep {result.sweep_id} · sweep-toy" and parent.params["command"] == spec.command()

    # the same command again, through the CLI: finished cells are skipped, failed ones run again
    cli = CliRunner().invoke(main, [
        "sweep", "--learners", "sweep-boom,sweep-steps", "--tasks", "sweep-toy", "--seeds", "2-4", "--max-trials", "2",
        "--eval-episodes", "2", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"])
    assert cli.exit_code == 1, cli.output
    assert f"sweep {result.sweep_id}: 0 finished, 3 skipped (finished before), 3 failed" in cli.stdout
    assert "sweep-boom-sweep-toy-s3: FAILED (RuntimeError: boom in the learner)" in cli.stdout
    assert "error: 3 cell(s) failed (see above); re-run the same command" in cli.stderr and "Traceback" not in cli.output
    runs = children_by_cell(mlflow_uri, result)
    assert [len(runs[("sweep-steps", s)]) for s in (2, 3, 4)] == [1, 1, 1]  # not re-run
    assert [len(runs[("sweep-boom", s)]) for s in (2, 3, 4)] == [2, 2, 2]  # re-run once each


def test_a_dying_cell_process_is_reported_and_the_sweep_goes_on(plugins, mlflow_uri):
    spec = SweepSpec(("sweep-crash", "sweep-steps"), ("sweep-toy",), (2,), max_trials=3, eval_episodes=1)
    result = run_sweep(spec, mlflow_uri, executor="local", workers=1)
    outcome = {o.cell.learner: o for o in result.outcomes}
    assert outcome["sweep-crash"].status == "failed"
    assert outcome["sweep-crash"].error.startswith("worker process died (the cell's process exited with code 3 before handing back")
    assert outcome["sweep-steps"].status == "finished" and outcome["sweep-steps"].solved  # the next cell ran
    crashed = Store(mlflow_uri).run(outcome["sweep-crash"].run_id)  # the run the dead worker had started
    assert crashed.status == "KILLED" and crashed.tags["harness.error"].startswith("worker process died")
    assert crashed.metrics["interaction_seconds"] == 4.0  # its first hand-over was logged before the crash
    # the driver ran the lost cell again twice (the learner cannot resume: afresh each time), then gave up
    assert "(ran 3 times)" in outcome["sweep-crash"].error
    assert [(r.cell.learner, r.node) for r in result.retries] == [("sweep-crash", None)] * 2
    assert all(r.run_id is not None and r.trials == 1 for r in result.retries)
    assert len(children_by_cell(mlflow_uri, result)[("sweep-crash", 2)]) == 3
    parent = Store(mlflow_uri).run(next(iter(result.parents.values()))[1])
    assert parent.tags["harness.cells_retried"] == "2" and parent.metrics["cells_retried"] == 2
    assert parent.tags["harness.cell_retries"].count("sweep-crash-sweep-toy-s2: worker lost (worker process died") == 2


def test_sigterm_to_the_driver_stops_the_workers_and_marks_the_runs_killed(plugins, mlflow_uri, tmp_path):
    """`kill DRIVER_PID` (SIGTERM to the driver alone): the driver stops its running workers, each
    marks its run KILLED (resumable), the parent is KILLED and the command exits with 130."""
    import signal

    args = ["sweep", "--learners", "sweep-slow", "--tasks", "sweep-toy", "--seeds", "0-1",
            "--max-trials", "5000", "--eval-episodes", "1", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"]
    spec = SweepSpec(("sweep-slow",), ("sweep-toy",), (0, 1), max_trials=5000, eval_episodes=1)
    with HarnessProcess(args, tmp_path) as proc:
        wait_until_cells_run(mlflow_uri, spec, proc, timeout=120)
        proc.signal(signal.SIGTERM)
        code = proc.wait(timeout=180)  # workers get up to WORKER_STOP_SECONDS to mark their runs; a loaded CI machine is slow
        output = proc.output()
    assert code == 130, output
    assert "interrupted" in output and "Traceback" not in output
    assert sorted(r.status for r in sweep_runs(mlflow_uri, spec, "cell")) == ["KILLED", "KILLED"]
    assert [r.status for r in sweep_runs(mlflow_uri, spec, "sweep")] == ["KILLED"]


def test_sigusr1_to_the_driver_drains_the_sweep(plugins, mlflow_uri, tmp_path):
    """`kill -USR1 DRIVER_PID`: no more cells start, each running cell stops once its trial in progress is
    stored (its run KILLED, nothing of a later trial logged), the parent is KILLED and the command says how to
    continue (exit 130)."""
    import re
    import signal
    import time

    args = ["sweep", "--learners", "sweep-slow", "--tasks", "sweep-toy", "--seeds", "0-2",
            "--max-trials", "5000", "--eval-episodes", "1", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"]
    spec = SweepSpec(("sweep-slow",), ("sweep-toy",), (0, 1, 2), max_trials=5000, eval_episodes=1)
    with HarnessProcess(args, tmp_path) as proc:
        deadline = time.time() + 120
        while not (len(cells := sweep_runs(mlflow_uri, spec, "cell")) == 2 and all(r.history("interaction_seconds") for r in cells)):
            assert time.time() < deadline, f"two cells did not start in time:\n{proc.output()}"
            time.sleep(0.5)
        proc.signal(signal.SIGUSR1)
        code = proc.wait(timeout=180)
        output = proc.output()
    assert code == 130, output
    assert "0 failed, 2 stopped as asked, 1 not started" in output and "Traceback" not in output
    assert "re-run the same command to continue" in output
    cells = sweep_runs(mlflow_uri, spec, "cell")
    assert sorted(int(r.tags["seed"]) for r in cells) == [0, 1] and {r.status for r in cells} == {"KILLED"}
    for run in cells:
        stopped_at = re.search(rf"sweep-slow-sweep-toy-s{run.tags['seed']}: stopped after trial (\d+) as asked \(SIGUSR1\)", output)
        assert stopped_at, output
        assert max(run.history("eval_cost")) == int(stopped_at[1])
        # in the UI: stopped, not failed; sweep-slow keeps no checkpoint, so the next invocation starts it again
        assert run.tags["harness.resumable"] == "false" and "**Stopped before its limit**" in run.tags["mlflow.note.content"]
        assert "Not resumable (no checkpoint)" in run.tags["mlflow.note.content"]
    (parent,) = sweep_runs(mlflow_uri, spec, "sweep")
    assert parent.status == "KILLED" and parent.tags["harness.cells_stopped"] == "2"


def test_the_sweep_prints_its_pid_and_a_stop_request_at_once_drains_it(plugins, mlflow_uri, tmp_path):
    """A sweep says how to stop it by its pid (also with --quiet: one run in the background is stopped that way), and
    `kill -USR1` sent as soon as that line appears, before the driver has opened the store, is a stop request, not the
    signal's default action: exit 130, nothing failed, the cells not started (or stopped after a trial)."""
    import signal

    args = ["sweep", "--learners", "sweep-slow", "--tasks", "sweep-toy", "--seeds", "0-2",
            "--max-trials", "5000", "--eval-episodes", "1", "--workers", "2", "--tracking-uri", mlflow_uri, "--quiet"]
    with HarnessProcess(args, tmp_path) as proc:
        marker = f"to stop (resumable): kill -USR1 {proc.proc.pid} "
        proc.wait_for(marker, timeout=60)
        proc.signal(signal.SIGUSR1)
        code = proc.wait(timeout=180)
        output = proc.output()
    assert code == 130, output
    assert "0 failed" in output and "Traceback" not in output and "re-run the same command to continue" in output
