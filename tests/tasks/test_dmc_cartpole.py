"""dm_control cartpole swing-up task: model facts, observation mapping, seeding, rewards, success."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pytest

pytest.importorskip("dm_control", reason="dm_control is the 'dmc' extra")

import tasks  # noqa: E402,F401  (registers the gymnasium ids)
from harness.errors import InteractionError, InvalidActionError  # noqa: E402
from harness.task import Episode  # noqa: E402
from tasks.dmc_cartpole import (  # noqa: E402
    GEAR,
    PHYSICS_TIMESTEP,
    POLE_LENGTH,
    DMCCartpole,
    pole_tip,
    swingup_observation_moments,
    swingup_reward,
)


@pytest.fixture(scope="module")
def env():
    environment = DMCCartpole().make_env()
    yield environment
    environment.close()


def set_state(physics, qpos, qvel) -> None:
    with physics.reset_context():
        physics.data.qpos[:] = qpos
        physics.data.qvel[:] = qvel


def test_model_constants_match_the_suite_xml(env):
    model = env.physics.named.model
    assert env.physics.timestep() == PHYSICS_TIMESTEP
    assert model.actuator_gear["slide", 0] == GEAR
    np.testing.assert_array_equal(model.actuator_ctrlrange["slide"], [-1.0, 1.0])
    assert 2 * model.geom_size["pole_1", 1] == pytest.approx(POLE_LENGTH)  # capsule half-length 0.5


def test_pole_tip_from_observation_matches_mujoco_geometry(env):
    """The cost's tip (x + l sin th, l cos th) is the pole's far end in MuJoCo's world frame (rail at z = 1)."""
    rng = np.random.default_rng(0)
    physics = env.physics
    for _ in range(10):
        set_state(physics, [rng.uniform(-1, 1), rng.uniform(-np.pi, np.pi)], rng.normal(size=2))
        state = env._flatten(env._dm_env.task.get_observation(physics))
        pole_origin = physics.named.data.xpos["pole_1"]
        pole_axis = physics.named.data.xmat["pole_1"].reshape(3, 3)[:, 2]
        tip_world = pole_origin + POLE_LENGTH * pole_axis
        np.testing.assert_allclose(pole_tip(state), [tip_world[0], tip_world[2] - 1.0], atol=1e-12)


def test_observation_maps_dm_control_observation_and_joint_state(env):
    rng = np.random.default_rng(1)
    env.reset(seed=1)
    for _ in range(5):
        _, _, _, _, info = env.step(rng.uniform(-1, 1, 1))
        dm_obs = env._dm_env.task.get_observation(env.physics)
        np.testing.assert_array_equal(info["state"], np.r_[dm_obs["position"], dm_obs["velocity"]])
        (x, th), (xd, thd) = env.physics.data.qpos, env.physics.data.qvel
        np.testing.assert_allclose(info["state"], [x, math.cos(th), math.sin(th), xd, thd], atol=1e-12)


def test_gymnasium_check_env_and_registration():
    made = gymnasium.make("harness/DMCCartpoleSwingup-v0", horizon=5)
    try:
        from gymnasium.utils.env_checker import check_env

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            check_env(made.unwrapped, skip_render_check=True)
        obs, _ = made.reset(seed=0)
        assert obs.shape == (5,) and made.unwrapped.task_spec.horizon == 5
    finally:
        made.close()


def test_seeding_is_deterministic():
    environment = DMCCartpole(measurement_noise=0.01).make_env()
    try:
        def rollout(seed):
            rng = np.random.default_rng(seed)
            out = [environment.reset(seed=seed)[0]]
            for _ in range(10):
                out.append(environment.step(rng.uniform(-1, 1, 1))[0])
            return np.array(out)

        a, b, c = rollout(3), rollout(3), rollout(4)
        np.testing.assert_array_equal(a, b)
        assert not np.allclose(a[0], c[0])
    finally:
        environment.close()


def test_start_distribution_matches_the_spec(env):
    spec = DMCCartpole().spec
    starts = np.array([env.reset(seed=s)[1]["state"] for s in range(2000)])
    mean, cov = swingup_observation_moments()
    np.testing.assert_array_equal(spec.init_mean, mean)
    np.testing.assert_array_equal(spec.init_cov, cov)
    assert spec.init_mean[1] == pytest.approx(-1.0, abs=1e-4)
    assert np.all(np.abs(starts.mean(axis=0) - mean) <= 4 * np.sqrt(np.diag(cov) / 2000) + 1e-12)
    np.testing.assert_allclose(starts.var(axis=0), np.diag(cov), rtol=0.15)
    # the closed forms against a direct Monte-Carlo of the suite's recipe
    e = np.random.default_rng(0).normal(0.0, 0.01, 200_000)
    assert np.mean(np.cos(np.pi + e)) == pytest.approx(mean[1], abs=5 * math.sqrt(cov[1, 1] / e.size))
    assert np.var(np.cos(np.pi + e)) == pytest.approx(cov[1, 1], rel=0.02)
    assert np.var(np.sin(np.pi + e)) == pytest.approx(cov[2, 2], rel=0.02)


def test_reward_is_minus_tip_cost(env):
    spec = DMCCartpole().spec
    rng = np.random.default_rng(2)
    env.reset(seed=2)
    for _ in range(20):
        _, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 1))
        assert not terminated
        assert reward == -float(spec.cost(info["state"]))
        tip = pole_tip(info["state"])
        distance2 = tip[0] ** 2 + (tip[1] - POLE_LENGTH) ** 2
        assert reward == pytest.approx(-(1 - math.exp(-distance2 / (2 * 0.25**2))), abs=1e-14)
    assert DMCCartpole(cost_width=0.5).spec.cost.width == 0.5


def test_dmc_reward_is_the_suite_reward_summed_over_the_repeat():
    from dm_control import suite

    environment = DMCCartpole(action_repeat=4).make_env()
    reference = suite.load("cartpole", "swingup", task_kwargs={"random": 5})
    try:
        environment.reset(seed=5)
        reference.reset()
        rng = np.random.default_rng(5)
        for _ in range(8):
            u = rng.uniform(-1, 1, 1)
            _, _, _, _, info = environment.step(u)
            expected = sum(reference.step(u).reward for _ in range(4))
            assert info["dmc_reward"] == pytest.approx(expected, abs=1e-12)
            assert 0.0 <= info["dmc_reward"] <= 4.0
    finally:
        environment.close()


def test_direct_mujoco_stepping_equals_dm_control_over_200_steps():
    """The env steps MuJoCo directly; dm_control's own Environment.step is the reference.

    Same seed, same 200 random actions (action repeat 10): the observations (qpos, qvel, xmat
    entries) are bit-identical and the summed suite rewards agree to 1e-12.
    """
    from dm_control import suite

    environment = DMCCartpole(horizon=200).make_env(measurement_noise=False)
    reference = suite.load("cartpole", "swingup", task_kwargs={"random": 11, "time_limit": float("inf")})
    try:
        obs, _ = environment.reset(seed=11)
        ref_obs = reference.reset().observation
        np.testing.assert_array_equal(obs, np.r_[ref_obs["position"], ref_obs["velocity"]])
        rng = np.random.default_rng(11)
        worst_reward = 0.0
        for _ in range(200):
            u = rng.uniform(-1.2, 1.2, 1)  # some beyond the bounds: both paths clip to [-1, 1]
            obs, _, _, _, info = environment.step(u)
            steps = [reference.step(np.clip(u, -1.0, 1.0)) for _ in range(10)]
            ref_obs = steps[-1].observation
            np.testing.assert_array_equal(obs, np.r_[ref_obs["position"], ref_obs["velocity"]])
            worst_reward = max(worst_reward, abs(info["dmc_reward"] - sum(t.reward for t in steps)))
        assert worst_reward < 1e-12
        assert environment.physics.data.time == pytest.approx(reference.physics.data.time, abs=1e-12)
    finally:
        environment.close()
        reference.close()


def test_swingup_reward_equals_the_suite_reward_function(env):
    """swingup_reward on floats against dm_control's Balance._get_reward on the same physics state."""
    rng = np.random.default_rng(12)
    physics, task = env.physics, env._dm_env.task
    cases = [(0.0, np.pi, 0.0, 0.0), (0.3, 0.2, 1.0, -7.0), (-2.0, 3.0, -1.0, 5.0)]
    cases += [(rng.uniform(-3, 3), rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1), rng.normal(0, 5)) for _ in range(50)]
    for x, th, u, thd in cases:
        set_state(physics, [x, th], [rng.normal(), thd])
        physics.set_control([u])
        expected = task.get_reward(physics)
        got = swingup_reward(x, float(physics.named.data.xmat["pole_1", "zz"]), u, thd)
        assert got == pytest.approx(expected, abs=1e-15)


def test_dt_is_action_repeat_times_physics_step():
    task = DMCCartpole(action_repeat=5)
    assert task.spec.dt == pytest.approx(0.05) and task.spec.horizon == 200 and task.success_steps == 20
    default = DMCCartpole().spec
    assert default.dt == pytest.approx(0.1) and default.horizon == 100 and default.options["horizon"] == 100
    environment = task.make_env()
    try:
        environment.reset(seed=0)
        t0 = environment.physics.data.time
        for _ in range(3):
            environment.step(np.zeros(1))
        assert environment.physics.data.time - t0 == pytest.approx(3 * 0.05)
    finally:
        environment.close()


def test_horizon_truncates_and_invalid_actions_raise():
    environment = DMCCartpole(horizon=3).make_env()
    try:
        environment.reset(seed=0)
        with pytest.raises(InvalidActionError):
            environment.step(np.array([np.nan]))
        with pytest.raises(InvalidActionError):
            environment.step(np.zeros(2))
        _, _, _, truncated, info = environment.step(np.array([3.0]))
        assert info["action_clipped"] and not truncated
        environment.step(0.0)
        _, _, terminated, truncated, _ = environment.step(np.zeros(1))
        assert truncated and not terminated
        with pytest.raises(InteractionError):
            environment.step(np.zeros(1))
    finally:
        environment.close()


def test_reset_to_a_given_state(env):
    x0 = np.array([0.3, math.cos(0.4), math.sin(0.4), -0.2, 1.5])
    obs, info = env.reset(options={"state": x0})
    np.testing.assert_allclose(info["state"], x0, atol=1e-12)


def upright_episode(steps: int, final: np.ndarray | None = None, terminated: bool = False) -> Episode:
    states = np.tile([0.1, 0.999, math.sqrt(1 - 0.999**2), 0.0, 0.0], (steps + 1, 1))
    if final is not None:
        states[-len(final):] = final
    return Episode(observations=states.copy(), states=states, actions=np.zeros((steps, 1)),
                   costs=np.zeros(steps), terminated=terminated)


def test_success_predicate_pass_and_fail():
    task = DMCCartpole()
    assert task.success(upright_episode(100))
    assert task.success(upright_episode(10))
    assert not task.success(upright_episode(9))
    assert not task.success(upright_episode(100, terminated=True))
    tilted = [0.0, 0.99, math.sqrt(1 - 0.99**2), 0.0, 0.0]
    assert not task.success(upright_episode(100, final=np.array([tilted])))
    off_centre = [0.3, 1.0, 0.0, 0.0, 0.0]
    assert not task.success(upright_episode(100, final=np.array([off_centre])))
    # a tilt 10 states before the end is outside the final second: still a success
    episode = upright_episode(100)
    episode.states[-11] = tilted
    assert task.success(episode)


def test_render_rgb_array():
    environment = DMCCartpole().make_env(render_mode="rgb_array")
    try:
        environment.reset(seed=0)
        try:
            image = environment.render()
        except Exception as error:  # no usable OpenGL (EGL) on this machine
            pytest.skip(f"MuJoCo rendering unavailable: {error}")
        assert image.dtype == np.uint8 and image.shape == (240, 320, 3) and image.std() > 0
    finally:
        environment.close()


def test_dm_control_is_not_imported_by_the_task_package():
    code = "import sys, tasks, tasks.dmc_cartpole; tasks.dmc_cartpole.DMCCartpole().spec; " \
           "sys.exit(1 if 'dm_control' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
