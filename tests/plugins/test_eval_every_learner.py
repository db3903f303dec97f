"""`harness eval RUN_ID` on a run of every learner: the saved policy (data only) is the one the run evaluated."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from harness.cli import main
from harness.runner import RunConfig, run
from harness.seeding import derive_seeds
from harness.tracking import MlflowTracker

PILCO_TINY = {"num_centres": "4", "policy_max_evaluations": "6", "gp_max_evals": "20", "plots": "false", "sample_particles": "0"}
#: tiny SAC / PPO (as tests/plugins/test_sb3_learners.py): a hand-over every 40 / 80 steps
SAC_SMALL = {"net_width": "16", "batch_size": "16", "learning_starts": "10", "eval_every_steps": "40"}
PPO_SMALL = {"net_width": "16", "batch_size": "40", "n_steps": "80", "n_epochs": "2"}
MC_PILCO_TINY = {"num_centres": "4", "particles": "16", "max_steps": "8", "window": "4", "gp_max_evals": "20"}
LEARNERS = [("random", {}), ("pilco", PILCO_TINY), ("pilco-mean", PILCO_TINY), ("mc-pilco", MC_PILCO_TINY), ("sac", SAC_SMALL),
            ("ppo", PPO_SMALL)]


@pytest.mark.parametrize("learner, options", LEARNERS, ids=[name for name, _ in LEARNERS])
def test_eval_tests_the_policy_the_run_evaluated(tmp_path, mlflow_uri, learner, options):
    if learner in ("sac", "ppo"):
        pytest.importorskip("stable_baselines3")
    seed = 11
    config = RunConfig(learner, "cartpole", seed=seed, learner_options=options, task_options={"horizon": 10}, max_trials=2,
                       eval_episodes=3)
    result = run(config, tracker=MlflowTracker(mlflow_uri))
    out = tmp_path / "eval"
    # the run's own evaluation episodes: same initial states, so a deterministic policy gives the run's last eval_cost
    args = ["eval", result.run_id, "--episodes", "3", "--seed", str(derive_seeds(seed)["evaluation"]), "--out", str(out),
            "--tracking-uri", mlflow_uri]
    outcome = CliRunner().invoke(main, args)
    assert outcome.exit_code == 0, outcome.output
    summary = json.loads((out / "test_summary.json").read_text())
    assert summary["policy"] == "policies/policy_trial002.policy" and summary["learner"] == learner
    if learner == "random":  # its generator went on drawing after the evaluation: a fresh draw, in the bounds
        assert 0 <= summary["mean_cost"] <= 10
    else:
        assert summary["mean_cost"] == result.history[-1]["eval_cost"]
    first = CliRunner().invoke(main, [*args[:-4], "--trial", "1", "--out", str(tmp_path / "first"), "--tracking-uri", mlflow_uri])
    assert first.exit_code == 0 and "policy_trial001.policy" in first.output, first.output
