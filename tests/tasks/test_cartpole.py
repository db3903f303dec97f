"""Cart-pole task: equations against a sympy Lagrangian, energy, env contract, cost, success."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
import sympy as sp
from gymnasium.utils.env_checker import check_env

import tasks  # noqa: F401  (registers the gymnasium ids)
from harness.errors import InvalidActionError, OptionError
from harness.task import Episode
from harness.testing import TaskConformance
from tasks.cartpole import CartPole, CartPoleParams, cartpole_energy, cartpole_rhs, pole_tip
from tasks.simulation import rk4_zoh


def lagrangian_accelerations(params: CartPoleParams):
    """(xdd, thdd) as a numeric function of (x, xd, thd, th, f), from an independent Lagrangian.

    Cart (mass M) at (x, 0); uniform rod (mass m, length l) hinged at the cart, theta = 0 hanging
    down: centre of mass at (x + l/2 sin th, -l/2 cos th), inertia m l^2 / 12 about it.
    Generalised forces: f - b xd on x, none on theta.
    """
    t = sp.symbols("t")
    f = sp.symbols("f")
    big_m, m, l, b, g = (sp.nsimplify(v) for v in (params.cart_mass, params.pole_mass, params.pole_length,
                                                    params.friction, params.gravity))
    x, th = sp.Function("x")(t), sp.Function("th")(t)
    cx, cy = x + l / 2 * sp.sin(th), -l / 2 * sp.cos(th)
    kinetic = big_m * x.diff(t) ** 2 / 2 + m * (cx.diff(t) ** 2 + cy.diff(t) ** 2) / 2 + m * l**2 / 24 * th.diff(t) ** 2
    lag = kinetic - m * g * cy
    forces = {x: f - b * x.diff(t), th: 0}
    eqs = [sp.diff(lag.diff(q.diff(t)), t) - lag.diff(q) - forces[q] for q in (x, th)]
    qdd = sp.symbols("xdd thdd")
    xs, xds, ths, thds = sp.symbols("x xd th thd")
    subs = {x.diff(t, 2): qdd[0], th.diff(t, 2): qdd[1]}
    eqs = [e.subs(subs) for e in eqs]
    eqs = [e.subs({x.diff(t): xds, th.diff(t): thds}).subs({x: xs, th: ths}) for e in eqs]
    sol = sp.solve(eqs, qdd, dict=True)[0]
    return sp.lambdify((xs, xds, thds, ths, f), [sol[qdd[0]], sol[qdd[1]]], "math")


@pytest.mark.parametrize("pole_length,friction", [(0.5, 0.1), (0.6, 0.0)])
def test_rhs_matches_sympy_lagrangian(pole_length, friction):
    params = CartPoleParams(pole_length=pole_length, friction=friction)
    accel = lagrangian_accelerations(params)
    rng = np.random.default_rng(0)
    for _ in range(20):
        z = [rng.uniform(-2, 2), rng.uniform(-3, 3), rng.uniform(-10, 10), rng.uniform(-np.pi, np.pi)]
        u = [rng.uniform(-10, 10)]
        xd, xdd, thdd, thd = cartpole_rhs(params)(z, u)
        exp_xdd, exp_thdd = accel(*z, u[0])
        assert (xd, thd) == (z[1], z[2])
        assert xdd == pytest.approx(exp_xdd, rel=1e-9, abs=1e-9)
        assert thdd == pytest.approx(exp_thdd, rel=1e-9, abs=1e-9)


def test_energy_conserved_without_friction_and_control():
    task = CartPole()
    params = CartPoleParams(friction=0.0)
    z = [0.3, 0.8, 4.0, 2.0]
    e0 = cartpole_energy(z, params)
    energies = []
    rhs = cartpole_rhs(params)
    for _ in range(100):  # 10 s at dt = 0.1 with the task's default sub-steps
        z = rk4_zoh(rhs, z, [0.0], task.dt, task.options["substeps"])
        energies.append(cartpole_energy(z, params))
    drift = max(abs(e - e0) for e in energies) / abs(e0)
    assert drift < 1e-6
    # friction removes energy: the check can fail
    z = [0.3, 0.8, 4.0, 2.0]
    lossy = CartPoleParams(friction=0.1)
    rhs = cartpole_rhs(lossy)
    for _ in range(100):
        z = rk4_zoh(rhs, z, [0.0], task.dt, task.options["substeps"])
    assert cartpole_energy(z, lossy) < e0 - 1e-3


def test_spec_defaults_are_v09():
    spec = CartPole().spec
    assert spec.dt == 0.1 and spec.horizon == 40 and spec.episode_seconds == pytest.approx(4.0)
    assert spec.angle_indices == (3,)
    np.testing.assert_array_equal(spec.action_high, [10.0])
    np.testing.assert_allclose(spec.init_cov, 0.1**2 * np.eye(4), rtol=1e-15)
    np.testing.assert_array_equal(spec.measurement_noise_std, np.full(4, 0.01))
    assert spec.cost.width == 0.25


def test_cost_is_tip_distance_to_upright():
    for length in (0.5, 0.6):
        task = CartPole(pole_length=length)
        rng = np.random.default_rng(1)
        x = rng.normal(size=(50, 4)) * [1, 1, 1, 3]
        tip = pole_tip(x, length)
        d2 = tip[:, 0] ** 2 + (tip[:, 1] - length) ** 2
        # reference formula of loss_cp.m: d^2 = (x + l sin th)^2 + l^2 (1 + cos th)^2
        d2_ref = (x[:, 0] + length * np.sin(x[:, 3])) ** 2 + length**2 * (1 + np.cos(x[:, 3])) ** 2
        np.testing.assert_allclose(d2, d2_ref, rtol=1e-12)
        np.testing.assert_allclose(task.spec.cost(x), 1 - np.exp(-d2 / (2 * 0.25**2)), rtol=1e-12, atol=1e-15)
    upright = np.array([0.0, 0.0, 0.0, math.pi])
    assert CartPole().spec.cost(upright) == pytest.approx(0.0, abs=1e-15)


def test_options_validated():
    assert CartPole(pole_length="0.6").spec.cost.target[1] == 0.6
    with pytest.raises(OptionError):
        CartPole(pole_lenght=0.6)
    with pytest.raises(OptionError):
        CartPole(horizon=0)


def test_check_env_direct_and_via_gymnasium_make():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded observation / non-normalised action warnings
        check_env(CartPole().make_env(render_mode="rgb_array"))
        env = gymnasium.make("harness/CartPoleSwingUp-v0", render_mode="rgb_array", pole_length=0.6)
        check_env(env.unwrapped)
        assert env.unwrapped.task_spec.cost.target[1] == 0.6
        env.reset(seed=0)
        frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 2  # something was drawn


def test_reward_is_minus_cost_of_true_state_and_obs_is_noisy():
    task = CartPole()
    env = task.make_env()
    obs, info = env.reset(seed=3)
    rng = np.random.default_rng(3)
    offsets = []
    for _ in range(40):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-10, 10, size=1))
        assert -reward == task.spec.cost(info["state"])
        offsets.append(obs - info["state"])
    assert truncated and not terminated
    offsets = np.array(offsets)
    assert 0.006 < offsets.std() < 0.014  # std 0.01 noise on the observation only
    quiet = task.make_env(measurement_noise=False)
    obs, info = quiet.reset(seed=3)
    np.testing.assert_array_equal(obs, info["state"])


def test_truncation_after_horizon():
    env = CartPole(horizon=12).make_env()
    env.reset(seed=0)
    flags = [env.step([0.0])[3] for _ in range(12)]
    assert flags == [False] * 11 + [True]


def _episode(states: np.ndarray) -> Episode:
    t = states.shape[0] - 1
    return Episode(observations=states, states=states, actions=np.zeros((t, 1)), costs=np.zeros(t))


def _upright(length: float, n: int, x: float = 0.0) -> np.ndarray:
    return np.tile([x, 0.0, 0.0, math.pi], (n, 1))


def test_success_predicate():
    task = CartPole()
    hanging = np.zeros((31, 4))
    good = np.vstack([hanging, _upright(0.5, 10)])
    assert task.success(_episode(good))
    bad_step = good.copy()
    bad_step[-3, 3] = 0.0  # hanging down at step -3
    assert not task.success(_episode(bad_step))
    off_9cm = np.vstack([hanging, _upright(0.5, 10, x=0.09)])
    assert not task.success(_episode(off_9cm))
    off_7cm = np.vstack([hanging, _upright(0.5, 10, x=0.07)])
    assert task.success(_episode(off_7cm))
    short = np.vstack([hanging[:1], _upright(0.5, 9)])  # only 9 steps recorded
    assert not task.success(_episode(short))
    terminated = _episode(good)
    terminated.terminated = True
    assert not task.success(terminated)
    # the predicate uses the true states, not the observations
    noisy = _episode(good)
    noisy.observations = noisy.observations + 1.0
    assert task.success(noisy)


def test_success_rules_consecutive_and_final():
    """Balanced for 10 steps mid-episode, then fallen: a success under Kamthe & Deisenroth's
    "ten consecutive time steps", a failure under ``success_rule=final``."""
    hanging = np.zeros((15, 4))
    mid = np.vstack([hanging, _upright(0.5, 10), hanging])
    assert CartPole().success(_episode(mid))
    assert not CartPole(success_rule="final").success(_episode(mid))
    gap = mid.copy()
    gap[20, 3] = 0.0  # one step out splits the run into 5 + 4
    assert not CartPole().success(_episode(gap))
    with pytest.raises(OptionError, match="success_rule"):
        CartPole(success_rule="sometimes")


def test_invalid_and_clipped_actions():
    env = CartPole().make_env()
    env.reset(seed=0)
    with pytest.raises(InvalidActionError):
        env.step([float("nan")])
    with pytest.raises(InvalidActionError):
        env.step(np.zeros(2))
    _, _, _, _, info = env.step([25.0])
    assert info["action_clipped"] and env.clipped_actions == 1
    _, _, _, _, info = env.step(np.array([9.0]))
    assert not info["action_clipped"] and env.clipped_actions == 1
    # the clipped action acts as the bound
    a, b = CartPole().make_env(), CartPole().make_env()
    a.reset(seed=5)
    b.reset(seed=5)
    np.testing.assert_array_equal(a.step([100.0])[4]["state"], b.step([10.0])[4]["state"])


def _rollout(seed: int) -> tuple[np.ndarray, np.ndarray]:
    env = CartPole().make_env()
    obs, info = env.reset(seed=seed)
    observations, states = [obs], [info["state"]]
    for k in range(40):
        obs, _, _, _, info = env.step([10.0 * math.sin(0.3 * k)])
        observations.append(obs)
        states.append(info["state"])
    return np.array(observations), np.array(states)


def test_seeding():
    o1, s1 = _rollout(11)
    o2, s2 = _rollout(11)
    o3, s3 = _rollout(12)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(s1, s2)
    assert not np.allclose(s1[0], s3[0])
    assert not np.allclose(o1, o3)


def test_initial_distribution():
    env = CartPole().make_env(measurement_noise=False)
    starts = np.array([env.reset(seed=s)[1]["state"] for s in range(2000)])
    np.testing.assert_allclose(starts.mean(axis=0), 0.0, atol=0.01)
    np.testing.assert_allclose(np.cov(starts.T), 0.01 * np.eye(4), atol=0.002)


class TestConformance(TaskConformance):
    """The harness's own plugin conformance checks."""

    task_cls = CartPole
