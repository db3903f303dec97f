"""`harness sweep`: cross product, local and Ray executors, resuming, failure isolation, validation."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from harness import sweep
from harness.cli import main
from harness.errors import HarnessError, OptionError
from harness.sweep import SWEEP_EXPERIMENT, SweepSpec, child_runs, format_seeds, parse_seeds, run_sweep
from harness.tracking import open_client
from tests.harness import sweep_site

# seeds 2, 3, 4 of `sweep-steps` with --max-trials 2: solved after 4 s, solved after 8 s, unsolved at 8 s
EXPECTED_STEPS = {2: (True, 4.0), 3: (True, 8.0), 4: (False, None)}


@pytest.fixture(scope="module")
def plugin_paths(tmp_path_factory) -> list[str]:
    return sweep_site.install(tmp_path_factory.mktemp("sweep-plugins"))


@pytest.fixture
def plugins(plugin_paths, monkeypatch) -> list[str]:
    sweep_site.activate(plugin_paths, monkeypatch)
    return plugin_paths


def children_by_cell(uri: str, result) -> dict[tuple[str, int], list]:
    client = open_client(uri)
    out: dict[tuple[str, int], list] = {}
    for run in child_runs(client, result.experiment_id, result.parent_run_id):
        out.setdefault((run.data.tags["learner"], int(run.data.tags["seed"])), []).append(run)
    return out


def check_steps_cells(uri: str, result) -> None:
    runs = children_by_cell(uri, result)
    for seed, (solved, time_to_success) in EXPECTED_STEPS.items():
        (run,) = [r for r in runs[("sweep-steps", seed)] if r.info.status == "FINISHED"]
        assert run.data.tags["solved"] == str(solved).lower()
        assert run.data.tags["harness.sweep_id"] == result.sweep_id and run.data.tags["harness.role"] == "cell"
        assert run.data.params["spec.state_dim"] == "1" and run.data.params["max_trials"] == "2"
        if solved:
            assert run.data.metrics["interaction_time_to_success"] == time_to_success
        else:
            assert "interaction_time_to_success" not in run.data.metrics
            assert run.data.metrics["interaction_seconds_total"] == 8.0


# ---- spec ---------------------------------------------------------------------------------------


def test_seed_ranges_and_identity():
    assert parse_seeds("0-3,7, 9-10") == (0, 1, 2, 3, 7, 9, 10)
    assert format_seeds((10, 9, 7, 0, 1, 2, 3)) == "0-3,7,9-10"
    for bad in ("", "a", "3-1", "1-"):
        with pytest.raises(OptionError):
            parse_seeds(bad)
    a = SweepSpec(("pilco", "sac"), ("cartpole",), (0, 1, 2), (("horizon", "30"),), max_trials=5)
    b = SweepSpec(("sac", "pilco"), ("cartpole",), (2, 1, 0), (("horizon", "30"),), max_trials=5)
    c = SweepSpec(("sac", "pilco"), ("cartpole",), (2, 1, 0), (("horizon", "31"),), max_trials=5)
    assert a.sweep_id == b.sweep_id != c.sweep_id
    assert len(a.cells()) == 6 and a.cells()[0] == sweep.Cell("pilco", "cartpole", 0)
    assert a.command() == "harness sweep --learners pilco,sac --tasks cartpole --seeds 0-2 --max-trials 5 --set horizon=30"


def test_scoped_assignments_apply_to_their_learner_only():
    spec = SweepSpec(("random", "pilco"), ("cartpole",), (0,), (("random:scale", "0.5"), ("cartpole:horizon", "20")))
    assert spec.assignments_for("random", "cartpole") == [("scale", "0.5"), ("horizon", "20")]
    assert spec.assignments_for("pilco", "cartpole") == [("horizon", "20")]
    with pytest.raises(OptionError, match="'sac' is none of this sweep's learners"):
        SweepSpec(("random",), ("cartpole",), (0,), (("sac:x", "1"),)).assignments_for("random", "cartpole")


def test_bad_input_fails_before_the_store_is_touched(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    # an option only `random` knows, applied to every cell: the pilco cell rejects it
    with pytest.raises(OptionError, match="unknown option 'scale'.*pilco on cartpole.*NAME:key=value"):
        run_sweep(SweepSpec(("random", "pilco"), ("cartpole",), (0,), (("scale", "0.5"),)), uri)
    with pytest.raises(HarnessError, match="unknown learner 'nope'"):
        run_sweep(SweepSpec(("nope",), ("cartpole",), (0,)), uri)
    with pytest.raises(OptionError, match="--max-trials must be >= 1"):
        run_sweep(SweepSpec(("random",), ("cartpole",), (0,), max_trials=0), uri)
    with pytest.raises(OptionError, match="--workers must be >= 1"):
        run_sweep(SweepSpec(("random",), ("cartpole",), (0,)), uri, workers=0)
    assert not (tmp_path / "mlflow.db").exists()


def test_missing_ray_is_one_line_with_the_pip_hint(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    with pytest.raises(HarnessError, match=r"pip install 'pilco-harness\[ray\]'"):
        sweep.check_executor("ray")


# ---- local executor -------------------------------------------------------------------------------


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
        assert boom.info.status == "FAILED" and boom.data.tags["harness.error"] == "RuntimeError: boom in the learner"
    client = open_client(mlflow_uri)
    parent = client.get_run(result.parent_run_id)
    assert parent.info.status == "FAILED" and parent.data.tags["harness.cells_failed"] == "3"
    assert parent.info.experiment_id == client.get_experiment_by_name(SWEEP_EXPERIMENT).experiment_id
    assert parent.data.params["command"] == spec.command()

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


def test_a_dying_worker_process_is_reported_and_replaced(plugins, mlflow_uri):
    spec = SweepSpec(("sweep-crash", "sweep-steps"), ("sweep-toy",), (2,), max_trials=3, eval_episodes=1)
    result = run_sweep(spec, mlflow_uri, executor="local", workers=1)
    outcome = {o.cell.learner: o for o in result.outcomes}
    assert outcome["sweep-crash"].status == "failed" and "worker process died (BrokenProcessPool" in outcome["sweep-crash"].error
    assert outcome["sweep-steps"].status == "finished" and outcome["sweep-steps"].solved  # ran in a fresh pool
    crashed = open_client(mlflow_uri).get_run(outcome["sweep-crash"].run_id)  # the run the dead worker had started
    assert crashed.info.status == "KILLED" and crashed.data.tags["harness.error"].startswith("worker process died")
    assert crashed.data.metrics["interaction_seconds"] == 4.0  # its first hand-over was logged before the crash


def test_interrupted_child_continues_from_its_checkpoint(plugins, mlflow_uri, monkeypatch):
    monkeypatch.setattr(sweep, "LocalPool", sweep_site.InlinePool)  # in-process: the driver's logic is under test
    spec = SweepSpec(("random", "sweep-steps"), ("sweep-toy",), (5,), max_trials=3, eval_episodes=1)
    first = run_sweep(spec, mlflow_uri)
    client = open_client(mlflow_uri)
    ids = {o.cell.learner: o.run_id for o in first.outcomes}
    costs = [m.value for m in client.get_metric_history(ids["random"], "eval_cost")]
    for run_id in ids.values():  # as if the driver had died: both children interrupted
        client.set_terminated(run_id, "KILLED")

    again = run_sweep(spec, mlflow_uri)
    outcome = {o.cell.learner: o for o in again.outcomes}
    # random supports resuming: the same child continues from its trial-2 checkpoint and ends identically
    assert outcome["random"].resumed and outcome["random"].run_id == ids["random"]
    assert client.get_run(ids["random"]).info.status == "FINISHED"
    history = sorted((m.step, m.value) for m in client.get_metric_history(ids["random"], "eval_cost"))
    assert [v for step, v in history if step == 3] == [costs[2], costs[2]]
    # sweep-steps cannot resume: a new child, the interrupted one stays KILLED
    assert not outcome["sweep-steps"].resumed and outcome["sweep-steps"].run_id != ids["sweep-steps"]
    assert client.get_run(ids["sweep-steps"]).info.status == "KILLED"
    assert len(children_by_cell(mlflow_uri, again)[("sweep-steps", 5)]) == 2
    assert len(children_by_cell(mlflow_uri, again)[("random", 5)]) == 1


def test_progress_view_reports_every_cell_and_the_totals(plugins, mlflow_uri, monkeypatch):
    monkeypatch.setattr(sweep, "LocalPool", sweep_site.InlinePool)
    from rich.console import Console

    console = Console(record=True, width=200, force_terminal=False)
    spec = SweepSpec(("sweep-steps", "sweep-boom"), ("sweep-toy",), (6,), max_trials=2, eval_episodes=1)
    updates = []

    class Recording(sweep.RichSweepProgress):
        def update(self, done, running, failed, eta_seconds):
            updates.append((done, running, failed, eta_seconds))
            super().update(done, running, failed, eta_seconds)

    run_sweep(spec, mlflow_uri, progress=Recording(console))
    text = console.export_text()
    assert "sweep-steps-sweep-toy-s6: not solved (max trials) after 8.0 s" in text
    assert "sweep-boom-sweep-toy-s6: FAILED (RuntimeError: boom in the learner)" in text
    assert updates[0] == (0, 1, 0, None) and updates[-1][:3] == (2, 0, 1) and updates[-1][3] == 0.0
    run_sweep(spec, mlflow_uri, progress=Recording(console))
    assert "1 of 2 cells already finished in an earlier invocation: skipped" in console.export_text()
    assert sweep.format_duration(3725) == "1:02:05" and sweep.format_duration(65) == "1:05" and sweep.format_duration(None) == "–"


# ---- Ray executor -------------------------------------------------------------------------------


def test_ray_sweep_gives_the_same_results(plugins, mlflow_uri):
    pytest.importorskip("ray")
    spec = SweepSpec(("sweep-steps", "random"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2)
    result = run_sweep(spec, mlflow_uri, executor="ray", workers=2)
    assert [o.status for o in result.outcomes] == ["finished"] * 6
    check_steps_cells(mlflow_uri, result)
    assert not any(o.solved for o in result.outcomes if o.cell.learner == "random")
    again = run_sweep(spec, mlflow_uri, executor="ray", workers=2)  # resumes: nothing left to run, Ray not started
    assert [o.status for o in again.outcomes] == ["skipped"] * 6 and again.parent_run_id == result.parent_run_id
