"""The integration path (RK4 + zero-order hold) and the generic ODE environment."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.errors import InteractionError, InvalidActionError, NumericalError
from harness.task import SaturatingCost, TaskSpec
from tasks.cartpole import CartPole
from tasks.double_pendulum import CartDoublePendulum
from tasks.simulation import OdeEnv, reference_step, rk4_zoh
from tasks.unicycle import Unicycle


def oscillator(z, u):
    """x'' = -4 x + u: exact solution known in closed form."""
    return (z[1], -4.0 * z[0] + u[0])


def oscillator_exact(z0, u, t):
    """Closed form of :func:`oscillator` with constant u (omega = 2, equilibrium u / 4)."""
    eq = u / 4.0
    x0, v0 = z0[0] - eq, z0[1]
    return np.array([eq + x0 * math.cos(2 * t) + v0 / 2 * math.sin(2 * t), -2 * x0 * math.sin(2 * t) + v0 * math.cos(2 * t)])


def test_rk4_is_fourth_order_against_the_closed_form():
    z0, u, dt = [1.0, -0.5], 0.7, 0.5
    exact = oscillator_exact(z0, u, dt)
    errors = [np.max(np.abs(np.array(rk4_zoh(oscillator, z0, [u], dt, n)) - exact)) for n in (4, 8, 16, 32)]
    ratios = [errors[k] / errors[k + 1] for k in range(3)]
    assert all(14.0 < r < 18.0 for r in ratios), ratios  # 2^4 = 16


def test_zero_order_hold_and_reference_agree_on_a_linear_system():
    z0, u, dt = [0.3, 0.2], -1.5, 0.1
    exact = oscillator_exact(z0, u, dt)
    np.testing.assert_allclose(reference_step(oscillator, z0, [u], dt), exact, atol=1e-12)
    np.testing.assert_allclose(rk4_zoh(oscillator, z0, [u], dt, 200), exact, atol=1e-12)
    # z' = u: the held control integrates exactly
    assert rk4_zoh(lambda z, v: (v[0],), [1.0], [2.0], 0.25, 1) == [1.5]


def _sets(task, rng, n):
    spec = task.spec
    target = spec.init_mean.copy()
    target[list(spec.angle_indices)] = math.pi if task.name == "cartpole" else 0.0
    return {
        "start": rng.multivariate_normal(spec.init_mean, spec.init_cov, n),
        "target": rng.multivariate_normal(target, spec.init_cov, n),
    }


def _one_step_error(task, states, substeps, rng):
    spec = task.spec
    worst = 0.0
    for z in states:
        u = [float(rng.choice([spec.action_low[0], spec.action_high[0]]))]
        ref = reference_step(task.rhs, z, u, spec.dt)
        worst = max(worst, float(np.max(np.abs(np.array(rk4_zoh(task.rhs, z, u, spec.dt, substeps)) - ref))))
    return worst


@pytest.mark.parametrize(
    "task,default_bound,strict_substeps",
    [(CartPole(), 2e-8, 50), (CartDoublePendulum(), 1e-7, 40)],
    ids=["cartpole", "double-pendulum"],
)
def test_one_step_error_against_solve_ivp(task, default_bound, strict_substeps):
    """The figures of the table in tasks/simulation.py (30 states per set here, 100 there)."""
    rng = np.random.default_rng(7)
    for name, states in _sets(task, rng, 30).items():
        default = _one_step_error(task, states, task.options["substeps"], rng)
        strict = _one_step_error(task, states, strict_substeps, rng)
        coarse = _one_step_error(task, states, task.options["substeps"] // 4, rng)
        assert default < default_bound, (name, default)
        assert strict < 1e-8, (name, strict)
        assert coarse > 50 * default, (name, coarse, default)  # the check resolves the error


def test_box_error_at_default_substeps():
    """Fast states (angular rates up to 10 rad/s): the documented upper figures."""
    rng = np.random.default_rng(8)
    cp = CartPole()
    states = rng.uniform([-1, -3, -10, -np.pi], [1, 3, 10, np.pi], (30, 4))
    assert _one_step_error(cp, states, cp.options["substeps"], rng) < 2e-7
    dp = CartDoublePendulum()
    states = rng.uniform([-1, -3, -10, -10, -np.pi, -np.pi], [1, 3, 10, 10, np.pi, np.pi], (30, 6))
    assert _one_step_error(dp, states, dp.options["substeps"], rng) < 5e-5


def _toy_spec(horizon=5, noise=0.1):
    """A 2-state oscillator task with cost on x and bounds |u| <= 1."""
    cost = SaturatingCost(np.zeros((0, 2)), np.array([[1.0, 0.0]]), np.array([0.0]), 1.0)
    return TaskSpec(
        name="toy", state_names=("x", "v"), action_names=("u",), dt=0.1, horizon=horizon,
        action_low=np.array([-1.0]), action_high=np.array([1.0]), init_mean=np.array([1.0, 0.0]),
        init_cov=np.diag([0.04, 0.0]), angle_indices=(), cost=cost, measurement_noise_std=np.full(2, noise),
    )


def test_env_contract_on_a_toy_system():
    spec = _toy_spec()
    env = OdeEnv(spec, oscillator, substeps=50, left_region=lambda s: abs(s[0]) > 5.0)
    with pytest.raises(InteractionError):
        env.step([0.0])
    obs, info = env.reset(seed=0, options={"state": [0.5, 0.0]})
    np.testing.assert_array_equal(info["state"], [0.5, 0.0])
    assert not np.array_equal(obs, info["state"])  # noisy observation
    for k in range(5):
        obs, reward, terminated, truncated, info = env.step([0.4])
        assert reward == -spec.cost(info["state"])
        assert truncated == (k == 4) and not terminated
    np.testing.assert_allclose(info["state"], oscillator_exact([0.5, 0.0], 0.4, 0.5), atol=1e-10)
    with pytest.raises(InteractionError):
        env.step([0.0])
    with pytest.raises(InvalidActionError):
        env.reset(seed=0)
        env.step(["a"])
    # the zero-variance entry of init_cov stays at its mean
    starts = np.array([env.reset(seed=s)[1]["state"] for s in range(200)])
    assert np.all(starts[:, 1] == 0.0) and 0.15 < starts[:, 0].std() < 0.25


def test_termination_and_numerical_error():
    spec = _toy_spec(horizon=50)
    env = OdeEnv(spec, lambda z, u: (z[1], 100.0 * z[0]), substeps=10, left_region=lambda s: abs(s[0]) > 5.0)
    env.reset(seed=0)
    done = [env.step([0.0])[2] for _ in range(3)]
    assert done[-1]
    for rhs in (lambda z, u: (z[0] * z[0] * z[0], 0.0), lambda z, u: (z[0] ** 8, 0.0)):  # inf; OverflowError
        blow_up = OdeEnv(spec, rhs, substeps=10)
        blow_up.reset(seed=0, options={"state": [1e200, 0.0]})
        with pytest.raises(NumericalError):
            blow_up.step([0.0])
        with pytest.raises(InteractionError):  # the episode is over
            blow_up.step([0.0])


def test_noise_switch_and_render_modes():
    spec = _toy_spec()
    quiet = OdeEnv(spec, oscillator, substeps=5, measurement_noise=False)
    obs, info = quiet.reset(seed=1)
    np.testing.assert_array_equal(obs, info["state"])
    assert quiet.render() is None
    with pytest.raises(ValueError):
        OdeEnv(spec, oscillator, substeps=5, render_mode="human")
    with pytest.raises(ValueError):
        OdeEnv(spec, oscillator, substeps=5, render_mode="rgb_array")  # no drawing function


@pytest.mark.parametrize(
    "task,low,high",
    [
        (CartPole(), [-2, -5, -15, -7], [2, 5, 15, 7]),
        (CartDoublePendulum(), [-2, -5, -15, -15, -7, -7], [2, 5, 15, 15, 7, 7]),
        (Unicycle(), [-3] * 5 + [-2, -2, -1.7, -4, -9, -1.7, -9], [3] * 5 + [2, 2, 1.7, 4, 9, 1.7, 9]),
    ],
    ids=["cartpole", "double-pendulum", "unicycle"],
)
def test_fused_stepper_is_bit_identical_to_rk4_zoh_of_the_rhs(task, low, high):
    """The env's fused stepper performs rk4_zoh's arithmetic: equal floats, not just close ones.

    (Unicycle: angles up to 1.7 rad, so some steps start or pass through the absorbing fall region.)"""
    rng = np.random.default_rng(9)
    spec = task.spec
    for substeps in (1, 3, task.options["substeps"]):
        for _ in range(100):
            z = rng.uniform(low, high).tolist()
            u = rng.uniform(1.5 * spec.action_low, 1.5 * spec.action_high).tolist()
            fused, generic = task.stepper(z, u, spec.dt, substeps), rk4_zoh(task.rhs, z, u, spec.dt, substeps)
            assert np.array_equal(fused, generic, equal_nan=True)
    env = task.make_env()
    assert env._stepper is task.stepper
