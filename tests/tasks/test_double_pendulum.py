"""Cart-double-pendulum: equations against a sympy Lagrangian, energy, env contract, cost, success."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
import sympy as sp
from gymnasium.utils.env_checker import check_env

import tasks  # noqa: F401  (registers the gymnasium ids)
from harness.errors import InvalidActionError
from harness.task import Episode
from harness.testing import TaskConformance
from tasks.double_pendulum import (
    CartDoublePendulum,
    DoublePendulumParams,
    double_pendulum_energy,
    double_pendulum_rhs,
    link_tip,
)
from tasks.simulation import rk4_zoh


def lagrangian_accelerations(params: DoublePendulumParams):
    """(xdd, th1dd, th2dd) as a numeric function of (x, xd, w1, w2, th1, th2, f), from a Lagrangian.

    Cart (m1) at (x, 0); uniform link 1 (m2, l2) hinged at the cart, uniform link 2 (m3, l3) hinged
    at the end of link 1; absolute angles, theta = 0 upright, a positive angle leans towards -x:
    joint at (x - l2 sin th1, l2 cos th1). Inertia m l^2 / 12 about each centre. Generalised
    forces: f - b xd on x only.
    """
    t, f = sp.symbols("t f")
    m1, m2, m3, l2, l3, b, g = (sp.nsimplify(v) for v in (
        params.cart_mass, params.link1_mass, params.link2_mass, params.link1_length, params.link2_length,
        params.friction, params.gravity))
    x, th1, th2 = (sp.Function(n)(t) for n in ("x", "th1", "th2"))
    c1x, c1y = x - l2 / 2 * sp.sin(th1), l2 / 2 * sp.cos(th1)
    jx, jy = x - l2 * sp.sin(th1), l2 * sp.cos(th1)
    c2x, c2y = jx - l3 / 2 * sp.sin(th2), jy + l3 / 2 * sp.cos(th2)

    def speed2(px, py):
        return px.diff(t) ** 2 + py.diff(t) ** 2

    kinetic = (
        m1 * x.diff(t) ** 2 / 2
        + m2 * speed2(c1x, c1y) / 2 + m2 * l2**2 / 24 * th1.diff(t) ** 2
        + m3 * speed2(c2x, c2y) / 2 + m3 * l3**2 / 24 * th2.diff(t) ** 2
    )
    lag = kinetic - g * (m2 * c1y + m3 * c2y)
    forces = {x: f - b * x.diff(t), th1: 0, th2: 0}
    coords = (x, th1, th2)
    eqs = [sp.diff(lag.diff(q.diff(t)), t) - lag.diff(q) - forces[q] for q in coords]
    acc = sp.symbols("xdd th1dd th2dd")
    pos = sp.symbols("x_ th1_ th2_")
    vel = sp.symbols("xd_ w1_ w2_")
    eqs = [e.subs({q.diff(t, 2): a for q, a in zip(coords, acc)}) for e in eqs]
    eqs = [e.subs({q.diff(t): v for q, v in zip(coords, vel)}).subs(dict(zip(coords, pos))) for e in eqs]
    mass, rest = sp.linear_eq_to_matrix(eqs, acc)
    return sp.lambdify((pos[0], vel[0], vel[1], vel[2], pos[1], pos[2], f), (mass, rest), "numpy")


@pytest.mark.parametrize("friction", [0.1, 0.0])
def test_rhs_matches_sympy_lagrangian(friction):
    params = DoublePendulumParams(friction=friction)
    matrices = lagrangian_accelerations(params)
    rhs = double_pendulum_rhs(params)
    rng = np.random.default_rng(0)
    for _ in range(20):
        z = [rng.uniform(-2, 2), rng.uniform(-3, 3), rng.uniform(-10, 10), rng.uniform(-10, 10),
             rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)]
        u = [rng.uniform(-20, 20)]
        mass, rest = matrices(*z, u[0])
        expected = np.linalg.solve(np.array(mass, dtype=float), np.array(rest, dtype=float).ravel())
        out = rhs(z, u)
        assert (out[0], out[4], out[5]) == (z[1], z[2], z[3])
        np.testing.assert_allclose(out[1:4], expected, rtol=1e-9, atol=1e-9)


def test_energy_conserved_without_friction_and_control():
    task = CartDoublePendulum()
    params = DoublePendulumParams(friction=0.0)
    rhs = double_pendulum_rhs(params)
    start = [0.1, 0.5, 2.0, -1.5, 2.5, 2.0]
    z = start
    e0 = double_pendulum_energy(z, params)
    drift = 0.0
    for _ in range(200):  # 10 s at dt = 0.05 with the task's default sub-steps
        z = rk4_zoh(rhs, z, [0.0], task.dt, task.options["substeps"])
        drift = max(drift, abs(double_pendulum_energy(z, params) - e0))
    assert drift / abs(e0) < 1e-6
    # the energy function is not trivially constant: friction dissipates it
    lossy = DoublePendulumParams(friction=0.1)
    z = start
    for _ in range(200):
        z = rk4_zoh(double_pendulum_rhs(lossy), z, [0.0], task.dt, task.options["substeps"])
    assert double_pendulum_energy(z, lossy) < e0 - 1e-3


def test_spec_defaults_are_the_reference_settings():
    spec = CartDoublePendulum().spec
    assert spec.dt == 0.05 and spec.horizon == 100 and spec.episode_seconds == pytest.approx(5.0)
    assert spec.angle_indices == (4, 5)
    np.testing.assert_array_equal(spec.action_low, [-20.0])
    np.testing.assert_array_equal(spec.init_mean, [0, 0, 0, 0, math.pi, math.pi])
    np.testing.assert_allclose(np.diag(spec.init_cov), np.array([0.1, 0.1, 0.1, 0.1, 0.01, 0.01]) ** 2)
    np.testing.assert_array_equal(spec.measurement_noise_std, np.full(6, 0.01))
    assert spec.cost.width == 0.5


@pytest.mark.parametrize("cost_length", [0.6, 1.0])
def test_cost_is_tip_distance(cost_length):
    task = CartDoublePendulum(cost_link_length=cost_length)
    rng = np.random.default_rng(2)
    x = rng.normal(size=(50, 6)) * [1, 1, 1, 1, 3, 3]
    # loss_cdp.m: d^2 = (x - l1 sin th1 - l2 sin th2)^2 + (l1 cos th1 + l2 cos th2 - l1 - l2)^2
    d2 = (x[:, 0] - cost_length * (np.sin(x[:, 4]) + np.sin(x[:, 5]))) ** 2 + (
        cost_length * (np.cos(x[:, 4]) + np.cos(x[:, 5]) - 2)) ** 2
    np.testing.assert_allclose(task.spec.cost(x), 1 - np.exp(-d2 / (2 * 0.5**2)), rtol=1e-12, atol=1e-15)
    assert task.spec.cost(np.zeros(6)) == pytest.approx(0.0, abs=1e-15)
    # the success distance always uses the true 0.6 m links
    tip = link_tip(x, 0.6, 0.6)
    np.testing.assert_allclose(task.tip_distance(x), np.hypot(tip[:, 0], tip[:, 1] - 1.2))


def test_check_env_direct_and_via_gymnasium_make():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(CartDoublePendulum().make_env(render_mode="rgb_array"))
        env = gymnasium.make("harness/CartDoublePendulumSwingUp-v0", render_mode="rgb_array", horizon=20)
        check_env(env.unwrapped)
        assert env.unwrapped.task_spec.horizon == 20
        env.reset(seed=0)
        frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 2


def test_reward_is_minus_cost_of_true_state_and_obs_is_noisy():
    task = CartDoublePendulum()
    env = task.make_env()
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    offsets = []
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-20, 20, size=1))
        assert -reward == task.spec.cost(info["state"])
        offsets.append(obs - info["state"])
    assert truncated and not terminated
    assert 0.008 < np.std(offsets) < 0.012


def _episode(states: np.ndarray) -> Episode:
    t = states.shape[0] - 1
    return Episode(observations=states, states=states, actions=np.zeros((t, 1)), costs=np.zeros(t))


def test_success_predicate():
    task = CartDoublePendulum()
    hanging = np.tile([0, 0, 0, 0, math.pi, math.pi], (91, 1))
    upright = np.zeros((10, 6))
    good = np.vstack([hanging, upright])
    assert task.success(_episode(good))
    bad = good.copy()
    bad[-3, 5] = math.pi  # second link down at step -3
    assert not task.success(_episode(bad))
    off = good.copy()
    off[-10:, 0] = 0.13  # tip 13 cm to the side
    assert not task.success(_episode(off))
    near = good.copy()
    near[-10:, 0] = 0.11
    assert task.success(_episode(near))
    # 11 cm with cost_link_length = 1.0 would read differently; success uses the true geometry
    assert CartDoublePendulum(cost_link_length=1.0).success(_episode(near))
    # up for 10 steps, then down again: consecutive rule yes, final rule no
    mid = np.vstack([hanging, upright, hanging[:5]])
    assert CartDoublePendulum().success(_episode(mid))
    assert not CartDoublePendulum(success_rule="final").success(_episode(mid))


def test_invalid_and_clipped_actions():
    env = CartDoublePendulum().make_env()
    env.reset(seed=0)
    with pytest.raises(InvalidActionError):
        env.step([float("inf")])
    with pytest.raises(InvalidActionError):
        env.step([[1.0]])
    assert env.step([-30.0])[4]["action_clipped"]
    assert not env.step([20.0])[4]["action_clipped"]


def test_seeding():
    def rollout(seed):
        env = CartDoublePendulum().make_env()
        out = [env.reset(seed=seed)[0]]
        for k in range(30):
            out.append(env.step([20.0 * math.cos(0.5 * k)])[0])
        return np.array(out)

    np.testing.assert_array_equal(rollout(1), rollout(1))
    assert not np.allclose(rollout(1), rollout(2))


class TestConformance(TaskConformance):
    """The harness's own plugin conformance checks."""

    task_cls = CartDoublePendulum
