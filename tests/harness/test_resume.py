"""Checkpoints and resume: a run continued after an interruption equals an uninterrupted one."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from harness.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from harness.errors import CheckpointError, TrackingError
from harness.provenance import git_sha
from harness.runner import RunConfig, run
from tests.harness.trackers import DiesAfterLogging, InterruptAt, RefusesAt
from tests.processes import HarnessProcess, run_harness

PILCO_TINY = {"num_centres": "4", "policy_max_evaluations": "6", "gp_max_evals": "20", "plots": "false"}
NOT_WALL = lambda history: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in history]


@pytest.mark.parametrize(
    "learner,options,task_options",
    [("random", {}, {}), ("pilco", PILCO_TINY, {"horizon": 10}),
     # the planning horizon grows 3 -> 6 -> 10 over the trials: a resume must continue at the grown one
     ("pilco", {**PILCO_TINY, "planning_horizon": "3", "grow_horizon_below": "10"}, {"horizon": 10}),
     # the same under the survival rule: the horizon grows after the rollout, before the trial's search
     ("pilco", {**PILCO_TINY, "planning_horizon": "3", "grow_horizon_below": "10", "grow_horizon_on": "survival"},
      {"horizon": 10}),
     # and under the realised rule (a threshold every cart-pole episode meets)
     ("pilco", {**PILCO_TINY, "planning_horizon": "3", "grow_horizon_below": "10", "grow_horizon_on": "realised"},
      {"horizon": 10})],
)
def test_resumed_run_equals_uninterrupted_run(learner, options, task_options):
    config = RunConfig(learner, "cartpole", seed=4, learner_options=options, task_options=task_options, max_trials=4, eval_episodes=2)
    reference = run(config)

    tracker = InterruptAt(3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    assert tracker.status == "KILLED"
    resumed = run(config, tracker=tracker, resume_run_id=tracker.run_id)
    assert tracker.status == "FINISHED"
    assert NOT_WALL(resumed.history) == NOT_WALL(reference.history)
    assert resumed.interaction_seconds == reference.interaction_seconds
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2, 3, 4]
    # the code the resumed trials ran is recorded (the run's git_sha param is the start's); trial 3's
    # checkpoint was stored before the interrupt came with its metrics, so the run resumed at trial 4
    assert tracker.tags["git_sha.resumed_at_trial_4"] == git_sha()
    if "grow_horizon_below" in options:
        assert [h for _, h in sorted(tracker.metrics["planning_horizon"])][-4:] == [3.0, 6.0, 10.0, 10.0]


def test_a_trial_whose_metrics_the_store_refused_is_not_run_again():
    """The checkpoint is stored before the metrics: the resume logs the refused trial's record from it
    and goes on with the next trial; the run's error is the refused write, not the failed end."""
    config = RunConfig("pilco", "cartpole", seed=4, learner_options=PILCO_TINY, task_options={"horizon": 10}, max_trials=4,
                       eval_episodes=2)
    reference = run(config)
    tracker = RefusesAt(3)
    with pytest.raises(TrackingError, match="refused the metrics of step 3"):
        run(config, tracker=tracker)
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2]
    resumed = run(config, tracker=tracker.mended(), resume_run_id=tracker.run_id)
    assert "git_sha.resumed_at_trial_4" in tracker.tags  # trial 3 came from its checkpoint
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2, 3, 4]  # each once
    assert sorted(tracker.metrics["eval_cost"]) == [(i + 1, r["eval_cost"]) for i, r in enumerate(reference.history)]
    assert NOT_WALL(resumed.history) == NOT_WALL(reference.history) and tracker.status == "FINISHED"


def test_resume_refuses_other_settings():
    config = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1)
    tracker = InterruptAt(3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    other = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1, learner_options={"scale": "0.5"})
    with pytest.raises(CheckpointError, match="learner.scale: checkpoint 1.0 vs now 0.5"):
        run(other, tracker=tracker, resume_run_id=tracker.run_id)


def test_an_option_added_since_the_run_started_resumes_at_its_default(monkeypatch):
    """A checkpoint written before a learner gained an option resumes when the option is at its
    default (the run did what the default does), and is refused when it is set otherwise."""
    from harness.options import Option
    from plugins.random_learner import RandomLearner

    config = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1)
    tracker = InterruptAt(3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    monkeypatch.setattr(RandomLearner, "options", RandomLearner.options + (Option("newer", int, 7, "added later"),))
    other = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1, learner_options={"newer": "8"})
    with pytest.raises(CheckpointError, match="learner.newer: checkpoint None vs now 8"):
        run(other, tracker=tracker, resume_run_id=tracker.run_id)
    assert len(run(config, tracker=tracker, resume_run_id=tracker.run_id).history) == 3


def test_execution_options_may_change_on_resume_and_old_checkpoints_holding_them_resume(monkeypatch):
    """An execution option (threads, kernel: how, not what) is not part of a run's identity: a resume
    with another value continues, and so does a checkpoint written when it still was (its identity
    holds the key), while an ordinary option set otherwise is still refused."""
    from harness.options import Option
    from plugins.random_learner import RandomLearner

    monkeypatch.setattr(RandomLearner, "options", RandomLearner.options + (Option("workers", int, None, "how", execution=True),))
    config = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1, learner_options={"workers": "1"})
    tracker = InterruptAt(3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    checkpoint_path = tracker.root / tracker.list_artifacts("checkpoints")[-1]
    old = load_checkpoint(checkpoint_path)
    assert "learner.workers" not in old.identity
    old.identity["learner.workers"] = 1  # as a checkpoint from before the option was an execution option
    save_checkpoint(old, checkpoint_path)
    other = RunConfig("random", "cartpole", seed=1, max_trials=3, eval_episodes=1, learner_options={"workers": "2"})
    assert len(run(other, tracker=tracker, resume_run_id=tracker.run_id).history) == 3
    assert tracker.params["learner.workers"] == "1"  # logged once, at the run's start, as every option


def test_corrupt_checkpoint_is_detected(tmp_path):
    path = save_checkpoint(Checkpoint({"a": 1}, 1, [], {}, {}), tmp_path / "ckpt_trial001.ckpt")
    assert load_checkpoint(path).trial == 1
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)
    (tmp_path / "junk.pkl").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a harness checkpoint"):
        load_checkpoint(tmp_path / "junk.pkl")


def _metric_history(uri: str, run_id: str, key: str) -> list[float]:
    import mlflow

    by_step = {m.step: m.value for m in sorted(mlflow.MlflowClient(uri).get_metric_history(run_id, key), key=lambda m: m.timestamp)}
    return [by_step[s] for s in sorted(by_step)]  # a trial logged again after the resume counts once


def test_sigkill_mid_trial_then_resume_matches_uninterrupted(tmp_path, mlflow_uri):
    """A real `harness bench` process killed with SIGKILL after trial 2 is resumed with --resume."""
    import mlflow

    args = ["bench", "-l", "pilco", "-t", "cartpole", "--seed", "9", "--max-trials", "8", "--eval-episodes", "2",
            "--tracking-uri", mlflow_uri, "--set", "horizon=10"] + sum((["--set", f"{k}={v}"] for k, v in PILCO_TINY.items()), [])
    with HarnessProcess(args, tmp_path) as proc:
        # killed as soon as trial 2 shows: somewhere in trial 3 or a little later on an idle machine
        # (a tiny trial takes a fraction of a second), never after the last of the 8
        proc.wait_for("trial 2/8", timeout=240)
        proc.signal(signal.SIGKILL)
        proc.wait(timeout=30)

    mlflow.set_tracking_uri(mlflow_uri)
    killed = mlflow.search_runs(experiment_names=["cartpole"], filter_string="params.seed = '9' AND params.learner = 'pilco'")
    assert len(killed) == 1 and killed.iloc[0]["status"] == "RUNNING"  # SIGKILL: nobody marked it
    run_id = killed.iloc[0]["run_id"]

    code, output = run_harness([*args, "--resume"], tmp_path, timeout=600)
    assert code == 0, output
    assert run_id in output  # the same run continued
    assert "Downloading artifacts" not in output  # no MLflow bar for fetching the checkpoint

    code, output = run_harness([*args, "--quiet"], tmp_path, timeout=600)
    assert code == 0, output
    runs = mlflow.search_runs(experiment_names=["cartpole"], filter_string="params.seed = '9' AND params.learner = 'pilco'")
    assert len(runs) == 2 and set(runs["status"]) == {"FINISHED"}
    ref_id = next(r for r in runs["run_id"] if r != run_id)
    for key in ("eval_cost", "interaction_seconds", "J_after", "eval_success_rate"):
        assert _metric_history(mlflow_uri, run_id, key) == _metric_history(mlflow_uri, ref_id, key), key


def _bench_stopped_by(signum: int, seed: int, tmp_path: Path, mlflow_uri: str) -> tuple[int, str, str]:
    """A long `harness bench` (random learner) sent ``signum`` after its second trial: ``(exit code, output,
    run id)``, the run being the only one of that seed in the store and KILLED."""
    import mlflow

    args = ["bench", "-l", "random", "-t", "cartpole", "--seed", str(seed), "--max-trials", "5000", "--eval-episodes", "1",
            "--tracking-uri", mlflow_uri]
    with HarnessProcess(args, tmp_path) as proc:
        proc.wait_for("trial 2/5000", timeout=120)
        proc.signal(signum)
        code = proc.wait(timeout=60)
        output, pid = proc.output(), proc.proc.pid
    mlflow.set_tracking_uri(mlflow_uri)
    runs = mlflow.search_runs(experiment_names=["cartpole"], filter_string=f"params.seed = '{seed}' AND params.learner = 'random'")
    assert len(runs) == 1 and runs.iloc[0]["status"] == "KILLED", output
    assert f"kill -USR1 {pid} after the trial in progress" in output
    return code, output, runs.iloc[0]["run_id"]


def test_sigterm_marks_the_run_killed_and_prints_how_to_resume(tmp_path, mlflow_uri):
    """`kill PID` on `harness bench`: the Ctrl-C path (run KILLED, resume command), not an abrupt end."""
    code, err, run_id = _bench_stopped_by(signal.SIGTERM, 21, tmp_path, mlflow_uri)
    assert code == 130, err
    assert f"interrupted: run {run_id} marked KILLED; continue it with the same command plus --resume {run_id}" in err


def test_sigusr1_stops_bench_after_the_trial_in_progress_and_prints_how_to_resume(tmp_path, mlflow_uri):
    """`kill -USR1 PID` on `harness bench`: the run ends KILLED once a trial is stored, its newest checkpoint is
    that trial's, and nothing of a later trial was logged."""
    from harness.tracking import open_client

    code, err, run_id = _bench_stopped_by(signal.SIGUSR1, 23, tmp_path, mlflow_uri)
    assert code == 130, err
    client = open_client(mlflow_uri)
    last = max(m.step for m in client.get_metric_history(run_id, "eval_cost"))
    assert f"stopped after trial {last} as asked (SIGUSR1): run {run_id} marked KILLED; continue it with the same command plus --resume {run_id}" in err
    assert max(a.path for a in client.list_artifacts(run_id, "checkpoints")) == f"checkpoints/ckpt_trial{last:03d}.ckpt"


def test_a_trial_the_store_holds_but_no_checkpoint_is_repeated_on_resume_and_not_logged_twice():
    """The run dies after its last trial's metrics are stored (the last trial writes no checkpoint): the
    resume repeats that trial from trial 2's checkpoint, exactly, and the store keeps one record a trial."""
    config = RunConfig("random", "cartpole", seed=7, max_trials=3, eval_episodes=1)
    reference = run(config)
    tracker = DiesAfterLogging(3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2, 3]
    resumed = run(config, tracker=tracker, resume_run_id=tracker.run_id)
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2, 3]
    assert [v for _, v in tracker.metrics["eval_cost"]] == [h["eval_cost"] for h in reference.history]
    assert [h["eval_cost"] for h in resumed.history] == [h["eval_cost"] for h in reference.history]
