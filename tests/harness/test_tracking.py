"""The tracking store as every harness command opens it (`harness.tracking.open_client`)."""

from __future__ import annotations

import pytest

from harness.tracking import open_client


def _download_one(tmp_path, name: str) -> None:
    client = open_client(f"sqlite:///{tmp_path}/mlflow-{name}.db")
    run = client.create_run(client.create_experiment(name, artifact_location=str(tmp_path / name)))
    (tmp_path / "policy.txt").write_text("theta")
    client.log_artifact(run.info.run_id, str(tmp_path / "policy.txt"), "trial001")
    local = client.download_artifacts(run.info.run_id, "trial001/policy.txt", str(tmp_path))
    assert open(local).read() == "theta"


@pytest.mark.parametrize("setting, bar", [(None, False), ("true", True)])
def test_downloads_draw_no_progress_bar_unless_asked(tmp_path, capfd, monkeypatch, setting, bar):
    """Scripts that read saved runs (and `harness report`) fetch many artifacts; MLflow's bar per file
    buried their output. The environment variable still brings it back."""
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "unset")  # restored after the test
    monkeypatch.delenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR")
    if setting is not None:
        monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", setting)
    _download_one(tmp_path, f"bar-{setting}")
    assert ("Downloading artifacts" in capfd.readouterr().err) is bar


def test_a_store_file_replaced_under_a_run_is_named_with_the_way_back(tmp_path):
    """What `git stash` of a committed store did to two running benchmarks: SQLite refuses every write
    to a database file that was replaced while open. The error says so, once, with the resume command."""
    import shutil

    from harness.errors import TrackingError
    from harness.tracking import MlflowTracker

    db = tmp_path / "mlflow.db"
    tracker = MlflowTracker(f"sqlite:///{db}")
    run_id = tracker.start("cartpole", "pilco-cartpole-s0", {"seed": 0}, {})
    tracker.log_metrics({"interaction_seconds": 3.0, "eval_cost": float("nan")}, step=1)
    assert tracker.logged_steps("interaction_seconds") == {1} and tracker.logged_steps("eval_cost") == set()
    shutil.copy(db, tmp_path / "copy.db")
    (tmp_path / "copy.db").replace(db)  # a new file at the path; the run's connection holds the old one
    with pytest.raises(TrackingError) as refused:
        tracker.log_metrics({"interaction_seconds": 6.0}, step=2)
    message = str(refused.value)
    assert "refused to log the metrics of step 2" in message and "attempt to write a readonly database" in message
    assert "replaced or deleted while this process had it open" in message
    assert f"--resume {run_id}" in message and len(message.splitlines()) == 1


def test_a_run_deletes_an_artifact_it_no_longer_needs(mlflow_uri, tmp_path):
    """A learner that keeps only its newest checkpoints (``Learner.keep_checkpoints``) deletes the older
    ones from the store: the file is gone from the run's artifacts and from the disk."""
    from harness.tracking import MlflowTracker

    tracker = MlflowTracker(mlflow_uri)
    tracker.start("cartpole", "sac-cartpole-s0", {"seed": 0}, {})
    for trial in (1, 2):
        path = tmp_path / f"ckpt_trial00{trial}.ckpt"
        path.write_bytes(b"state %d" % trial)
        tracker.log_artifact(path, "checkpoints")
    tracker.delete_artifact("checkpoints/ckpt_trial001.ckpt")
    tracker.delete_artifact("checkpoints/ckpt_trial009.ckpt")  # absent: nothing happens
    assert tracker.list_artifacts("checkpoints") == ["checkpoints/ckpt_trial002.ckpt"]
    fetched = tracker.fetch_artifact("checkpoints/ckpt_trial002.ckpt", tmp_path / "back")
    assert fetched.read_bytes() == b"state 2"
