"""Runs stored by an older harness (pickled checkpoints, policies and PILCO model files): refused with the
command that converts them; `harness store migrate` converts them once; the run then resumes exactly."""

from __future__ import annotations

import hashlib
import pickle
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from harness.checkpoint import Checkpoint, load_checkpoint
from harness.cli import main
from harness.datafile import LegacyFormatError
from harness.discovery import load_learner
from harness.runner import RunConfig, run
from harness.task import Episode
from harness.tracking import MlflowTracker, open_client
from tasks.cartpole import CartPole
from tests.harness.trackers import InterruptedMlflow

PILCO_TINY = {"num_centres": "4", "policy_max_evaluations": "6", "gp_max_evals": "20", "plots": "false", "sample_particles": "0"}
NOT_WALL = lambda history: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in history]


def _artifact_dir(client, run_id: str) -> Path:
    uri = client.get_run(run_id).info.artifact_uri
    return Path(urlparse(uri).path if uri.startswith("file:") else uri)


def _as_older_harness_wrote_it(root: Path, learner: str) -> None:
    """Replace a run's checkpoints, policies and PILCO model files by what the harness wrote before the
    data-only format: pickles of the same objects (checkpoint: behind a HARNESS-CKPT header)."""
    from plugins.pilco.gp import GPHyperparameters
    from plugins.pilco.presets import Preset
    from plugins.pilco.propagate import StateLayout

    for path in sorted((root / "checkpoints").glob("*.ckpt")):
        new = load_checkpoint(path)
        interaction = {**new.interaction, "episodes": [Episode(**e) for e in new.interaction["episodes"]]}
        state = dict(new.learner)
        if "hyperparameters" in state:
            state["hyperparameters"] = GPHyperparameters.from_dict(state["hyperparameters"])
        payload = pickle.dumps(Checkpoint(new.identity, new.trial, new.history, interaction, state, new.rng, version=1))
        path.with_suffix(".pkl").write_bytes(b"HARNESS-CKPT\n" + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload)
        path.unlink()
    for path in sorted((root / "policies").glob("*.policy")):
        path.with_suffix(".pkl").write_bytes(pickle.dumps(load_learner(learner).load_policy(path, CartPole(horizon=10).spec)))
        path.unlink()
    for path in sorted(root.glob("trial*/model_trial*.pt")):
        saved = torch.load(path, weights_only=True)
        torch.save({**saved, "layout": StateLayout(**saved["layout"]), "preset": Preset(**saved["preset"])}, path)


@pytest.mark.parametrize("learner, options", [("random", {}), ("pilco", PILCO_TINY)])
def test_an_older_harness_run_is_refused_then_migrated_and_resumes_exactly(tmp_path, mlflow_uri, learner, options):
    config = RunConfig(learner, "cartpole", seed=6, learner_options=options, task_options={"horizon": 10}, max_trials=4, eval_episodes=2)
    reference = run(config)
    tracker = InterruptedMlflow(mlflow_uri, 3)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=tracker)
    run_id, client = tracker.run_id, open_client(mlflow_uri)
    root = _artifact_dir(client, run_id)
    _as_older_harness_wrote_it(root, learner)

    with pytest.raises(LegacyFormatError, match=f"checkpoint ckpt_trial003.pkl is in the harness's old pickled format, which can "
                                                f"run code when read: not loaded; .* `harness store migrate {run_id}`"):
        run(config, tracker=MlflowTracker(mlflow_uri), resume_run_id=run_id)
    assert client.get_run(run_id).info.status == "KILLED"  # still resumable, not left RUNNING
    refused = CliRunner().invoke(main, ["eval", run_id, "--episodes", "2", "--tracking-uri", mlflow_uri])
    assert refused.exit_code == 2 and "policy policy_trial003.pkl is in the harness's old pickled format" in refused.output
    if learner == "pilco":
        from plugins.pilco.saved_run import SavedPilcoRun

        with SavedPilcoRun(run_id, mlflow_uri) as saved, pytest.raises(LegacyFormatError, match="model_trial002.pt of run"):
            saved.saved_model(2)

    declined = CliRunner().invoke(main, ["store", "migrate", run_id, "--tracking-uri", mlflow_uri], input="n\n")
    assert declined.exit_code == 1 and "reading files in the old pickled format runs code" in declined.output
    assert not list((root / "checkpoints").glob("*.ckpt"))  # nothing read, nothing written
    migrated = CliRunner().invoke(main, ["store", "migrate", run_id, "--tracking-uri", mlflow_uri, "--yes"])
    assert migrated.exit_code == 0, migrated.output
    assert f"run {run_id}: checkpoints/ckpt_trial003.pkl -> checkpoints/ckpt_trial003.ckpt" in migrated.output
    assert f"run {run_id}: policies/policy_trial001.pkl -> policies/policy_trial001.policy" in migrated.output
    assert ("trial003/model_trial003.pt rewritten" in migrated.output) == (learner == "pilco")
    again = CliRunner().invoke(main, ["store", "migrate", run_id, "--tracking-uri", mlflow_uri, "--yes"])
    assert f"run {run_id}: nothing to convert" in again.output

    evaluated = CliRunner().invoke(main, ["eval", run_id, "--episodes", "2", "--out", str(tmp_path / "ev"), "--tracking-uri", mlflow_uri])
    assert evaluated.exit_code == 0 and "policy_trial003.policy" in evaluated.output, evaluated.output
    if learner == "pilco":
        with SavedPilcoRun(run_id, mlflow_uri) as saved:
            assert saved.saved_model(2)["layout"] == saved.policy(2).layout and saved.policy_trials() == [1, 2, 3]
    resumed = run(config, tracker=MlflowTracker(mlflow_uri), resume_run_id=run_id)
    assert NOT_WALL(resumed.history) == NOT_WALL(reference.history)
    assert resumed.interaction_seconds == reference.interaction_seconds


def test_migrate_all_finds_the_runs_with_old_files_and_checks_its_arguments(tmp_path):
    from harness.tracking import default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    old = run(RunConfig("random", "cartpole", seed=1, task_options={"horizon": 10}, max_trials=2, eval_episodes=1), tracker=MlflowTracker(uri))
    new = run(RunConfig("random", "cartpole", seed=2, task_options={"horizon": 10}, max_trials=1, eval_episodes=1), tracker=MlflowTracker(uri))
    client = open_client(uri)
    _as_older_harness_wrote_it(_artifact_dir(client, old.run_id), "random")
    both = CliRunner().invoke(main, ["store", "migrate", old.run_id, "--all", "--tracking-uri", uri])
    assert both.exit_code == 2 and "give the RUN_IDs to convert or --all (not both)" in both.output
    unknown = CliRunner().invoke(main, ["store", "migrate", "no-such-run", "--yes", "--tracking-uri", uri])
    assert unknown.exit_code == 2 and "no run 'no-such-run'" in unknown.output
    done = CliRunner().invoke(main, ["store", "migrate", "--all", "--yes", "--tracking-uri", uri])
    assert done.exit_code == 0 and old.run_id in done.output and new.run_id not in done.output, done.output
    assert "no run in" in CliRunner().invoke(main, ["store", "migrate", "--all", "--yes", "--tracking-uri", uri]).output


def test_an_sb3_zip_policy_is_converted_to_the_same_actions(tmp_path):
    """SB3 learners saved SB3's .zip (cloudpickled metadata); the conversion rebuilds the same network from data."""
    pytest.importorskip("stable_baselines3")
    from harness.interaction import Interaction
    from plugins.sb3_learners import SACLearner, make_agent_env

    task = CartPole(horizon=10)
    learner = SACLearner(task.spec, {"net_width": 16, "batch_size": 16, "learning_starts": 10}, seed=3)
    interaction = Interaction(task.make_env(), task.spec, seed=3)
    model = learner.build_model(make_agent_env(interaction.as_env(), task.spec), learner.hyperparameters())
    model.learn(30)
    model.save(tmp_path / "policy_trial001.zip")
    interaction.close()
    with pytest.raises(LegacyFormatError, match="policy_trial001.zip is in the harness's old pickled format"):
        SACLearner.load_policy(tmp_path / "policy_trial001.zip", task.spec)
    path = SACLearner.save_policy(SACLearner.read_legacy_policy(tmp_path / "policy_trial001.zip", task.spec), tmp_path / "policy_trial001")
    policy = SACLearner.load_policy(path, task.spec)
    probes = np.random.default_rng(0).normal(size=(5, 4))
    for x in probes:
        from plugins.sb3_learners import angle_features, to_bounds

        expected, _ = model.predict(angle_features(x, (3,)).astype(np.float32), deterministic=True)
        np.testing.assert_array_equal(policy(x), to_bounds(expected, task.spec.action_low, task.spec.action_high))
