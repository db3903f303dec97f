"""The SB3 learners (``sac``, ``ppo``): maps, accounting through the harness, budget, saving, seeding.

Small networks and a few hundred steps per test; real SB3 training, real cart-pole.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from harness import runner  # noqa: E402
from harness.discovery import load_task  # noqa: E402
from harness.errors import BudgetExhaustedError, OptionError  # noqa: E402
from harness.interaction import Interaction  # noqa: E402
from harness.runner import RunConfig  # noqa: E402
from harness.testing import LearnerConformance  # noqa: E402
from plugins.sb3_learners import (  # noqa: E402
    PPOLearner,
    SACLearner,
    SB3Policy,
    angle_features,
    feature_dim,
    from_bounds,
    make_agent_env,
    sac_entropy_coefficient,
    to_bounds,
    whole_episode_rollout,
)

#: tiny SAC: learns from step 10, trains after every (40-step) episode, hand-over every episode
SAC_SMALL = {"net_width": 16, "batch_size": 16, "learning_starts": 10, "eval_every_steps": 40}
#: tiny PPO: an update (and a hand-over) every 2 episodes
PPO_SMALL = {"net_width": 16, "batch_size": 40, "n_steps": 80, "n_epochs": 2}


@pytest.fixture
def cartpole():
    return load_task("cartpole")()


@pytest.fixture
def sb3_plugins(monkeypatch):
    learners = {"sac": SACLearner, "ppo": PPOLearner}
    monkeypatch.setattr(runner, "load_learner", lambda name: learners[name])


# -- observation and action maps -------------------------------------------------------------


def test_angle_features_replace_angles_by_sin_then_cos():
    x = np.array([1.0, -2.0, 3.0, 0.7, 4.0, -1.2])
    got = angle_features(x, (3, 5))
    want = [1.0, -2.0, 3.0, 4.0, np.sin(0.7), np.sin(-1.2), np.cos(0.7), np.cos(-1.2)]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
    assert feature_dim(6, (3, 5)) == got.shape[-1] == 8
    batch = np.stack([x, 2 * x])
    np.testing.assert_allclose(angle_features(batch, (3, 5))[1], angle_features(2 * x, (3, 5)))
    no_angles = angle_features(x, ())
    assert no_angles is not x and np.array_equal(no_angles, x)


def test_angle_features_are_periodic():
    x = np.array([0.3, 0.1, -0.5, 1.1])
    np.testing.assert_allclose(angle_features(x, (3,)), angle_features(x + [0, 0, 0, 2 * np.pi], (3,)), atol=1e-12)


def test_to_bounds_maps_the_unit_box_affinely_and_clips():
    low, high = np.array([-10.0, 0.0]), np.array([10.0, 50.0])
    np.testing.assert_allclose(to_bounds(np.array([-1.0, -1.0]), low, high), low)
    np.testing.assert_allclose(to_bounds(np.array([1.0, 1.0]), low, high), high)
    np.testing.assert_allclose(to_bounds(np.array([0.0, 0.5]), low, high), [0.0, 37.5])
    np.testing.assert_allclose(to_bounds(np.array([3.0, -7.0]), low, high), [10.0, 0.0])
    u = np.array([-3.3, 12.5])
    np.testing.assert_allclose(to_bounds(from_bounds(u, low, high), low, high), u, atol=1e-12)


def test_agent_env_sees_sin_cos_and_drives_the_system_in_control_units(cartpole):
    spec = cartpole.spec
    interaction = Interaction(cartpole.make_env(), spec, seed=4)
    env = make_agent_env(interaction.as_env(), spec)
    assert env.observation_space.shape == (5,) and env.action_space.shape == (1,)
    first, _ = env.reset()
    obs, *_ = env.step(np.array([1.0], dtype=np.float32))
    obs2, *_ = env.step(np.array([-0.5], dtype=np.float32))
    interaction.close()
    episode = interaction.episodes[0]
    np.testing.assert_allclose(episode.actions[:, 0], [10.0, -5.0])  # force limit 10 N
    for seen, raw in zip((first, obs, obs2), episode.observations):
        assert seen.dtype == np.float32
        np.testing.assert_allclose(seen, angle_features(raw, (3,)), rtol=1e-6, atol=1e-6)
    assert interaction.steps == 2


def _rollout_agent_env(task, gamma, action, seed=3):
    """One episode of a constant agent action through :func:`make_agent_env`: the agent's rewards and the recorded episode."""
    interaction = Interaction(task.make_env(), task.spec, seed=seed)
    env = make_agent_env(interaction.as_env(), task.spec, gamma)
    env.reset()
    rewards, done = [], False
    while not done:
        _, reward, terminated, truncated, _ = env.step(np.asarray(action, dtype=np.float32))
        rewards.append(reward)
        done = terminated or truncated
    interaction.close()
    return np.array(rewards), interaction.episodes[0]


@pytest.mark.parametrize("gamma", [1.0, 0.99, 0.9])
def test_an_early_fall_costs_the_agent_what_continuing_to_the_horizon_would(gamma):
    """The unicycle without torque falls before its horizon; the agent's discounted return equals the
    one of the recorded costs continued with the last cost up to the horizon (gamma = 1: minus the
    evaluation's horizon_cost), computed here from the episode; the interaction records the true costs."""
    task = load_task("unicycle")()
    rewards, episode = _rollout_agent_env(task, gamma, [0.0, 0.0])
    H = task.spec.horizon
    assert episode.terminated and 1 < episode.steps < H
    np.testing.assert_allclose(rewards[:-1], -episode.costs[:-1], rtol=1e-12)
    continued = np.concatenate([episode.costs, np.full(H - episode.steps, episode.costs[-1])])
    discounted = lambda r: float(np.sum(r * gamma ** np.arange(len(r))))
    assert discounted(rewards) == pytest.approx(-discounted(continued), rel=1e-12)
    if gamma == 1.0:
        assert rewards.sum() == pytest.approx(-episode.horizon_cost(H), rel=1e-12)


def test_episodes_that_reach_the_horizon_keep_their_rewards(cartpole):
    rewards, episode = _rollout_agent_env(cartpole, 0.99, [0.3])
    assert not episode.terminated and episode.steps == cartpole.spec.horizon
    np.testing.assert_array_equal(rewards, -episode.costs)


def test_the_learners_discount_the_held_cost_with_their_gamma(cartpole):
    """SB3 trains on the interaction through HeldCostAtTermination with the run's gamma."""
    from plugins.sb3_learners import HeldCostAtTermination

    learner, _, generator, interaction = _first_handover(SACLearner, {**SAC_SMALL, "gamma": "0.95"}, cartpole, seed=1)
    env = learner._model.get_env().envs[0]
    while not isinstance(env, HeldCostAtTermination):
        env = env.env
    generator.close()
    interaction.close()
    assert env.gamma == 0.95 and env.horizon == cartpole.spec.horizon


def test_agent_env_passes_sb3_env_checker(cartpole):
    from stable_baselines3.common.env_checker import check_env

    interaction = Interaction(cartpole.make_env(), cartpole.spec, seed=0)
    check_env(make_agent_env(interaction.as_env(), cartpole.spec), warn=True)
    counted = interaction.steps
    interaction.close()
    assert counted > 0 and counted == sum(ep.steps for ep in interaction.episodes)


class _RecordingModel:
    """Stands in for an SB3 model: remembers what it was shown, answers a fixed normalised action."""

    def __init__(self, action):
        self.action = np.asarray(action, dtype=np.float32)
        self.seen = []

    def predict(self, observation, deterministic=False):
        self.seen.append((np.array(observation), deterministic))
        return self.action, None


def test_policy_applies_the_same_maps_as_training(cartpole):
    model = _RecordingModel([0.25])
    policy = SB3Policy(model, cartpole.spec)
    x = np.array([0.1, -0.2, 0.3, 2.5])
    u = policy(x)
    np.testing.assert_allclose(u, [2.5])  # 0.25 of the way from 0 to 10 N
    seen, deterministic = model.seen[0]
    assert deterministic
    np.testing.assert_allclose(seen, angle_features(x, (3,)), rtol=1e-6)


# -- options and presets ---------------------------------------------------------------------


def test_presets_are_overridden_by_set_options(cartpole):
    spec = cartpole.spec
    sac = SACLearner(spec, {"learning_rate": "3e-4", "train_freq": "1"}).hyperparameters()
    assert sac["learning_rate"] == 3e-4 and sac["train_freq"] == 1 and sac["gradient_steps"] == -1
    assert sac["eval_every_steps"] == 5 * spec.horizon
    ppo = PPOLearner(spec, {"n_steps": 100, "eval_every_steps": 150}).hyperparameters()
    assert ppo["n_steps"] == 100 and ppo["eval_every_steps"] == 200  # rounded up to whole updates
    assert ppo["batch_size"] == 100 // 16
    default = PPOLearner(spec).hyperparameters()
    assert default["n_steps"] == default["eval_every_steps"] == 32 * 40 and default["batch_size"] == 80
    with pytest.raises(OptionError, match="n_steps"):
        SACLearner(spec, {"n_steps": 10})


@pytest.mark.parametrize("value, expected", [("auto", "auto"), ("auto_0.1", "auto_0.1"), ("0.02", 0.02), (0.5, 0.5)])
def test_sac_entropy_coefficient_forms(value, expected):
    assert sac_entropy_coefficient(value) == expected


@pytest.mark.parametrize("value", ["0", "-1", "auto_", "auto_0", "nan", "inf", "fixed", "auto-0.1"])
def test_sac_entropy_coefficient_rejects_bad_values_in_one_line(value):
    with pytest.raises(OptionError, match="'ent_coef' of learner 'sac' must be auto, auto_X or a number X > 0"):
        sac_entropy_coefficient(value)


@pytest.mark.parametrize("options, message", [({"ent_coef": "0"}, "'ent_coef' of learner 'sac' must be"),
                                              ({"gradient_steps": "0"}, "'gradient_steps' of learner 'sac' must be")])
def test_bad_sb3_arguments_are_refused_when_the_learner_is_built(cartpole, options, message):
    """Checked at construction, which the runner does before it starts a tracked run (no FAILED run is left)."""
    with pytest.raises(OptionError, match=message):
        SACLearner(cartpole.spec, options)


def test_sac_fixed_entropy_coefficient_reaches_sb3_and_its_checkpoint(cartpole):
    """``ent_coef=0.05`` builds SB3's SAC with that fixed coefficient (no tuning, no optimiser for it); the
    checkpoint then holds SB3's fixed tensor instead of log_ent_coef. The preset's "auto" tunes it."""
    fixed, _, generator, interaction = _first_handover(SACLearner, {**SAC_SMALL, "ent_coef": "0.05"}, cartpole, seed=1)
    generator.close()
    interaction.close()
    assert fixed._model.ent_coef_optimizer is None and float(fixed._model.ent_coef_tensor) == pytest.approx(0.05)
    state = fixed.state_dict()
    assert set(state["variables"]) == {"ent_coef_tensor"} and "ent_coef_optimizer" not in state["parameters"]
    assert SACLearner(cartpole.spec).hyperparameters()["ent_coef"] == "auto"


@pytest.mark.parametrize("horizon, n_steps", [(40, 1280), (100, 1600), (67, 1072), (30, 960), (500, 8000)])
def test_ppo_rollouts_are_whole_episodes_in_whole_minibatches(horizon, n_steps):
    got = whole_episode_rollout(horizon)
    assert got == n_steps and got % horizon == 0 and (got // horizon) % 16 == 0


def test_default_limits_are_budgets_not_trials():
    assert SACLearner.default_max_trials is None and PPOLearner.default_max_trials is None
    assert SACLearner.default_budget_seconds == 1e4 and PPOLearner.default_budget_seconds == 1e5


# -- the harness contract --------------------------------------------------------------------


class TestSACConformance(LearnerConformance):
    learner_cls = SACLearner
    learner_options = SAC_SMALL


class TestPPOConformance(LearnerConformance):
    learner_cls = PPOLearner
    learner_options = PPO_SMALL


@pytest.mark.parametrize("learner, options, chunk", [("sac", SAC_SMALL, 40), ("ppo", PPO_SMALL, 80)])
def test_evaluation_steps_are_not_counted(sb3_plugins, learner, options, chunk):
    few = runner.run(RunConfig(learner, "cartpole", seed=2, learner_options=options, max_trials=2, eval_episodes=1))
    many = runner.run(RunConfig(learner, "cartpole", seed=2, learner_options=options, max_trials=2, eval_episodes=4))
    dt = 0.1
    assert few.interaction_seconds == many.interaction_seconds == pytest.approx(2 * chunk * dt)
    for run in (few, many):
        assert [h["interaction_seconds"] for h in run.history] == pytest.approx([chunk * dt, 2 * chunk * dt])
        # the learner's own step counter agrees with the harness's seconds
        assert [h["sb3_num_timesteps"] * dt for h in run.history] == pytest.approx([chunk * dt, 2 * chunk * dt])
        assert all(h["sb3_steps_per_second"] > 0 for h in run.history)
        # mean summed cost of SB3's recent training episodes: 40 steps of a cost in [0, 1)
        assert all(0 < h["sb3_train_episode_cost"] < 40 for h in run.history)


@pytest.mark.parametrize("learner, options", [("sac", SAC_SMALL), ("ppo", PPO_SMALL)])
def test_budget_stops_the_run_inside_sb3(sb3_plugins, learner, options):
    # 6 s = 60 steps, less than one hand-over chunk of 100 steps: SB3 is stopped mid-learn()
    result = runner.run(RunConfig(learner, "cartpole", learner_options={**options, "eval_every_steps": 100}, budget_seconds=6.0))
    assert result.stop_reason == "budget" and not result.solved
    assert result.interaction_seconds == pytest.approx(6.0)
    assert result.interaction_time_to_success is None and result.trials == 0


def test_budget_error_propagates_out_of_learn(cartpole):
    learner = SACLearner(cartpole.spec, SAC_SMALL, seed=0)
    interaction = Interaction(cartpole.make_env(), cartpole.spec, budget_seconds=2.5, seed=0)
    generator = learner.learn(interaction)
    with pytest.raises(BudgetExhaustedError):
        next(generator)
    assert interaction.steps == 25
    interaction.close()


def _first_handover(learner_cls, options, task, seed):
    learner = learner_cls(task.spec, options, seed=seed)
    interaction = Interaction(task.make_env(), task.spec, seed=seed)
    generator = learner.learn(interaction)
    policy = next(generator)
    return learner, policy, generator, interaction


def _probes(spec, n=6):
    return np.random.default_rng(5).multivariate_normal(spec.init_mean, np.diag([1.0, 1.0, 4.0, 4.0]), size=n)


@pytest.mark.parametrize("learner_cls, options", [(SACLearner, SAC_SMALL), (PPOLearner, PPO_SMALL)])
def test_saved_policy_reloads_with_the_same_actions(cartpole, tmp_path, learner_cls, options):
    learner, policy, generator, interaction = _first_handover(learner_cls, options, cartpole, seed=1)
    path = learner.save_policy(policy, tmp_path / "policy_trial001")
    before = np.array([policy(x) for x in _probes(cartpole.spec)])
    generator.close()
    interaction.close()
    assert path.suffix == ".policy" and path.exists()  # data only: not SB3's .zip, whose metadata is cloudpickled
    reloaded = learner_cls.load_policy(path, cartpole.spec)
    after = np.array([reloaded(x) for x in _probes(cartpole.spec)])
    np.testing.assert_array_equal(before, after)
    assert np.all(np.abs(after) <= 10.0) and np.ptp(after) > 0  # in the bounds, not constant


def test_a_saved_sac_policy_holds_its_actor_only_and_older_full_saves_still_load(cartpole):
    """SAC's saved policy keeps the actor's tensors (the critics and their targets do not act: at the
    preset's 256x256 nets they are ~80 % of the bytes); a save of the whole network (older harness)
    loads with the same actions; a missing actor tensor or an unknown one is an error."""
    learner, policy, generator, interaction = _first_handover(SACLearner, SAC_SMALL, cartpole, seed=2)
    generator.close()
    interaction.close()
    state = SACLearner.policy_state(policy)
    full = policy.network.state_dict()
    assert state["weights"] and all(k.startswith("actor.") for k in state["weights"])
    assert set(state["weights"]) == {k for k in full if k.startswith("actor.")}
    assert 3 * sum(v.numel() for v in state["weights"].values()) < sum(v.numel() for v in full.values())
    probes = _probes(cartpole.spec)
    expected = np.array([policy(x) for x in probes])
    for weights in (state["weights"], {k: v.clone() for k, v in full.items()}):
        reloaded = SACLearner.policy_from_state({**state, "weights": weights}, cartpole.spec)
        np.testing.assert_array_equal(np.array([reloaded(x) for x in probes]), expected)
    missing = {k: v for k, v in state["weights"].items() if k != "actor.mu.weight"}
    with pytest.raises(ValueError, match=r"missing \['actor.mu.weight'\]"):
        SACLearner.policy_from_state({**state, "weights": missing}, cartpole.spec)
    with pytest.raises(ValueError, match="unexpected"):
        SACLearner.policy_from_state({**state, "weights": {**state["weights"], "extra.weight": full["actor.mu.weight"]}}, cartpole.spec)


@pytest.mark.parametrize("learner_cls, options", [(SACLearner, SAC_SMALL), (PPOLearner, PPO_SMALL)])
def test_same_seed_same_first_handover_other_seed_differs(cartpole, learner_cls, options):
    actions = {}
    for label, seed in (("a", 3), ("b", 3), ("c", 4)):
        _, policy, generator, interaction = _first_handover(learner_cls, options, cartpole, seed)
        actions[label] = np.array([policy(x) for x in _probes(cartpole.spec)])
        generator.close()
        interaction.close()
    np.testing.assert_array_equal(actions["a"], actions["b"])
    assert not np.array_equal(actions["a"], actions["c"])


def test_hyperparameters_are_attached_at_the_first_handover(cartpole):
    import json

    learner, _, generator, interaction = _first_handover(SACLearner, SAC_SMALL, cartpole, seed=0)
    (path,) = learner.artifacts
    saved = json.loads(path.read_text())
    generator.close()
    interaction.close()
    assert saved["algorithm"] == "SAC" and saved["task"] == "cartpole"
    assert saved["net_width"] == 16 and saved["eval_every_steps"] == 40 and saved["learning_rate"] == 1e-3
    assert not path.exists()  # the temporary copy is removed when the learner is closed


# -- resuming ---------------------------------------------------------------------------------

NOT_WALL = lambda history: [{k: v for k, v in r.items() if "second" not in k or k == "interaction_seconds"} for r in history]


@pytest.mark.parametrize("learner, options", [
    ("sac", {**SAC_SMALL, "buffer_size": 1000}),
    ("sac", {**SAC_SMALL, "buffer_size": 1000, "learning_starts": 150}),  # resumed in the random warm-up (steps 120-150)
    ("ppo", PPO_SMALL)])
def test_resumed_run_equals_uninterrupted_run_and_keeps_two_checkpoints(sb3_plugins, monkeypatch, learner, options):
    """Interrupted after trial 3 (SAC: past its random warm-up, replay buffer and entropy coefficient in
    use; PPO: gSDE noise, Adam moments) and resumed from trial 3's checkpoint: every later trial's
    record (evaluation, SB3's losses and counters) equals the uninterrupted run's exactly."""
    from plugins.sb3_learners import SB3Learner
    from tests.harness.trackers import InterruptAt

    monkeypatch.setattr(SB3Learner, "checkpoint_every_seconds", None)  # a checkpoint after every trial

    config = RunConfig(learner, "cartpole", seed=6, learner_options=options, max_trials=5, eval_episodes=2)
    reference = runner.run(config)
    tracker = InterruptAt(3)
    with pytest.raises(KeyboardInterrupt):
        runner.run(config, tracker=tracker)
    assert tracker.list_artifacts("checkpoints") == ["checkpoints/ckpt_trial002.ckpt", "checkpoints/ckpt_trial003.ckpt"]
    resumed = runner.run(config, tracker=tracker, resume_run_id=tracker.run_id)
    assert tracker.tags["git_sha.resumed_at_trial_4"]
    assert NOT_WALL(resumed.history) == NOT_WALL(reference.history)
    assert resumed.interaction_seconds == reference.interaction_seconds
    assert any("sb3_" in k and "loss" in k for k in resumed.history[-1])  # learning happened after the resume
    assert tracker.list_artifacts("checkpoints") == ["checkpoints/ckpt_trial003.ckpt", "checkpoints/ckpt_trial004.ckpt"]


def test_sac_checkpoint_holds_the_filled_replay_buffer(cartpole):
    learner, _, generator, interaction = _first_handover(SACLearner, {**SAC_SMALL, "buffer_size": 1000}, cartpole, seed=1)
    state = learner.state_dict()
    generator.close()
    interaction.close()
    replay = state["replay"]
    assert replay["pos"] == 40 and not replay["full"]
    assert replay["observations"].shape == (40, 1, 5) and replay["actions"].shape == (40, 1, 1)
    assert set(state["variables"]) == {"log_ent_coef"}
    assert set(state["parameters"]) == {"policy", "actor.optimizer", "critic.optimizer", "ent_coef_optimizer"}


def test_a_handover_in_the_middle_of_an_episode_stores_no_checkpoint(sb3_plugins, monkeypatch):
    """PPO's rollout of 60 steps on 40-step episodes hands over mid-episode at 60 and 180 steps: the
    system's state there is not saved, so only trial 2's (120 steps, an episode boundary) is stored."""
    from harness.tracking import MemoryTracker
    from plugins.sb3_learners import SB3Learner

    monkeypatch.setattr(SB3Learner, "checkpoint_every_seconds", None)
    tracker = MemoryTracker()
    result = runner.run(RunConfig("ppo", "cartpole", seed=1, learner_options={**PPO_SMALL, "n_steps": 60, "batch_size": 30},
                                  max_trials=4, eval_episodes=1), tracker=tracker)
    assert result.trials == 4 and result.interaction_seconds == pytest.approx(24.0)
    assert tracker.list_artifacts("checkpoints") == ["checkpoints/ckpt_trial002.ckpt"]


def test_checkpoints_wait_for_their_interval_but_a_stop_always_stores_one(sb3_plugins):
    """SB3 hand-overs come every few seconds and a checkpoint holds every recorded episode: one per
    ``checkpoint_every_seconds`` (300 s; none in this short run). ``kill -USR1`` arriving after trial 2's
    checkpoint was passed over (while its metrics are stored) still stops with trial 2 checkpointed, and
    the resumed run equals the uninterrupted one."""
    import os
    import signal

    from harness.interrupts import StopRequested
    from harness.tracking import MemoryTracker

    class StopAt(MemoryTracker):
        def log_metrics(self, metrics, step):
            super().log_metrics(metrics, step)
            if step == 2 and not getattr(self, "sent", False):
                self.sent = True
                os.kill(os.getpid(), signal.SIGUSR1)

    config = RunConfig("ppo", "cartpole", seed=3, learner_options=PPO_SMALL, max_trials=4, eval_episodes=1)
    quiet = MemoryTracker()
    reference = runner.run(config, tracker=quiet)
    assert quiet.list_artifacts("checkpoints") == []
    tracker = StopAt()
    with pytest.raises(StopRequested, match="after trial 2"):
        runner.run(config, tracker=tracker)
    assert tracker.list_artifacts("checkpoints") == ["checkpoints/ckpt_trial002.ckpt"]
    resumed = runner.run(config, tracker=tracker, resume_run_id=tracker.run_id)
    assert NOT_WALL(resumed.history) == NOT_WALL(reference.history)
