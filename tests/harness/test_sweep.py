"""`harness sweep`: the spec, validation, resuming and the progress view (in-process pool)."""

from __future__ import annotations

import pytest

from harness.errors import HarnessError, OptionError
from harness.store import Store
from harness.sweep import Cell, SweepSpec, format_seeds, parse_seeds, pools, run_sweep
from harness.sweep.progress import RichSweepProgress, SilentSweepProgress, TrialWatcher, format_duration
from tests.harness import sweep_site
from tests.harness.sweep_site import children_by_cell, plugin_paths, plugins  # noqa: F401 (fixtures)

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
    assert len(a.cells()) == 6 and a.cells()[0] == Cell("pilco", "cartpole", 0)
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
        pools.check_executor("ray")


# ---- in-process pool: the driver's logic -----------------------------------------------------


def test_interrupted_child_continues_from_its_checkpoint(plugins, mlflow_uri, monkeypatch):
    monkeypatch.setattr(pools, "LocalPool", sweep_site.InlinePool)  # in-process: the driver's logic is under test
    spec = SweepSpec(("random", "sweep-steps"), ("sweep-toy",), (5,), max_trials=3, eval_episodes=1)
    first = run_sweep(spec, mlflow_uri)
    store = Store(mlflow_uri)
    ids = {o.cell.learner: o.run_id for o in first.outcomes}
    costs = [m.value for m in store.client.get_metric_history(ids["random"], "eval_cost")]
    for run_id in ids.values():  # as if the driver had died: both children interrupted
        store.set_status(run_id, "KILLED")

    again = run_sweep(spec, mlflow_uri)
    outcome = {o.cell.learner: o for o in again.outcomes}
    # random supports resuming: the same child continues from its trial-2 checkpoint and ends identically
    assert outcome["random"].resumed and outcome["random"].run_id == ids["random"]
    assert store.run(ids["random"]).status == "FINISHED"
    history = sorted((m.step, m.value) for m in store.client.get_metric_history(ids["random"], "eval_cost"))
    # trial 3 (the last: no checkpoint) was logged before the "death"; the resume repeats it and does not log it twice
    assert [v for step, v in history if step == 3] == [costs[2]] and [s for s, _ in history] == [1, 2, 3]
    # sweep-steps cannot resume: a new child, the interrupted one stays KILLED
    assert not outcome["sweep-steps"].resumed and outcome["sweep-steps"].run_id != ids["sweep-steps"]
    assert store.run(ids["sweep-steps"]).status == "KILLED"
    assert len(children_by_cell(mlflow_uri, again)[("sweep-steps", 5)]) == 2
    assert len(children_by_cell(mlflow_uri, again)[("random", 5)]) == 1


def test_progress_view_reports_every_cell_and_the_totals(plugins, mlflow_uri, monkeypatch):
    monkeypatch.setattr(pools, "LocalPool", sweep_site.InlinePool)
    from rich.console import Console

    console = Console(record=True, width=200, force_terminal=False)
    spec = SweepSpec(("sweep-steps", "sweep-boom"), ("sweep-toy",), (6,), max_trials=2, eval_episodes=1)
    updates = []

    class Recording(RichSweepProgress):
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
    assert format_duration(3725) == "1:02:05" and format_duration(65) == "1:05" and format_duration(None) == "–"


def test_trial_watcher_reports_each_new_trial_of_running_cells_once(mlflow_uri):
    """The driver's view of long cells: new hand-overs of RUNNING children of every parent, read from the store."""
    store = Store(mlflow_uri)
    experiments = [store.ensure_experiment(name) for name in ("watcher-a", "watcher-b")]
    parents = [(e, store.create_run(e, "sweep x", {})) for e in experiments]
    child = lambda parent, name: store.create_run(parent[0], name, {"mlflow.parentRunId": parent[1], "learner": "pilco"})  # noqa: E731
    running, done, other = child(parents[0], "pilco · a · s0"), child(parents[0], "pilco · a · s1"), child(parents[1], "pilco · b · s0")
    store.log_params(running, {"max_trials": 10, "budget_seconds": None})  # as the runner logs a run's limits
    store.log_params(other, {"max_trials": None, "budget_seconds": 2000.0})

    def log_trial(run_id, step, seconds):
        store.log_metrics(run_id, {"interaction_seconds": seconds, "eval_success_rate": 0.5, "eval_cost": 12.0, "wall_seconds": 7.0 * step,
                                   "J_after": 20.0 - step}, step=step)

    log_trial(running, 1, 4.0)
    log_trial(running, 2, 8.0)
    log_trial(done, 1, 4.0)
    store.set_status(done, "FINISHED")
    log_trial(other, 1, 4.0)
    seen = []

    records = []

    class Recording(SilentSweepProgress):
        def trial(self, label, learner, record):
            seen.append((label, learner, record["trial"], record["interaction_seconds"]))
            records.append(record)

    watcher = TrialWatcher(store, parents, poll_seconds=20.0)
    watcher.poll(Recording(), now=100.0)
    # the newest trial only, of the running children of both parents; finished children are not watched
    assert seen == [("pilco · a · s0", "pilco", 2, 8.0), ("pilco · b · s0", "pilco", 1, 4.0)]
    # each record carries the run's limits and its wall time at the trial before (none before the first)
    assert records[0]["max_trials"] == 10 and "budget_seconds" not in records[0] and records[0]["previous_wall_seconds"] == 7.0
    assert records[1]["budget_seconds"] == 2000.0 and "max_trials" not in records[1] and "previous_wall_seconds" not in records[1]
    log_trial(running, 3, 12.0)
    watcher.poll(Recording(), now=110.0)  # within the poll interval: the store is not read
    assert len(seen) == 2
    watcher.poll(Recording(), now=121.0)
    watcher.poll(Recording(), now=142.0)  # nothing new: nothing printed
    assert seen[2:] == [("pilco · a · s0", "pilco", 3, 12.0)]

    from rich.console import Console

    console = Console(record=True, width=200, force_terminal=False)
    record = {"trial": 3, "interaction_seconds": 12.0, "eval_success_rate": 0.5, "eval_cost": 12.0, "wall_seconds": 21.0, "J_after": 17.0}
    RichSweepProgress(console).trial("pilco · a · s0", "pilco", record)  # what PILCO declares it logs: J
    assert "pilco · a · s0: trial 3 | 12.0 s interaction | success 50% | eval cost 12.00 | J 17.00 | wall 21 s" in console.export_text()
    RichSweepProgress(console).trial("pilco · a · s0", "pilco", records[2])  # the watcher's record: limits, the trial's own wall
    assert "pilco · a · s0: trial 3/10 | 12.0 s interaction | success 50% | eval cost 12.00 | J 17.00 | wall 21 s (trial 7 s)" in console.export_text()
    RichSweepProgress(console).trial("pilco · b · s0", "pilco", records[1])
    assert "pilco · b · s0: trial 1 | 4.0/2000 s interaction |" in console.export_text()


class _StoppedWhileRunning(sweep_site.InlinePool):
    """A worker that started its cell's run and was then stopped without marking it (a force-killed
    process, a Ray task whose cancelled result came back first); the next wait is the user's Ctrl-C."""

    store = None

    def submit(self, job):
        self.store.create_run(job.experiment_id, "stopped", {
            "mlflow.parentRunId": job.parent_run_id, "learner": job.cell.learner, "task": job.cell.task, "seed": str(job.cell.seed)})
        return object()

    def wait(self, handles, timeout):
        raise KeyboardInterrupt


def test_ctrl_c_marks_the_runs_of_cells_in_flight_killed(plugins, mlflow_uri, monkeypatch):
    store = Store(mlflow_uri)
    monkeypatch.setattr(_StoppedWhileRunning, "store", store)
    monkeypatch.setattr(pools, "LocalPool", _StoppedWhileRunning)
    spec = SweepSpec(("sweep-steps",), ("sweep-toy",), (11,), max_trials=2, eval_episodes=1)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(spec, mlflow_uri)
    (child,) = store.search([store.experiment_id("sweep-toy")], "attributes.run_name = 'stopped'")
    assert child.status == "KILLED"  # resumable by the next invocation, not left RUNNING
    assert [r.status for r in sweep_site.sweep_runs(mlflow_uri, spec, "sweep")] == ["KILLED"]
