"""Sine moments at large variances: the cause of the "not positive-definite" failures in policy search.

The unicycle (linear policy, trapezoid squashing) and the cart-double-pendulum (RBF policy) died in
``torch.linalg.cholesky`` ("leading minor of order 1 is not positive-definite") during policy
search. No variance had become negative: the sine-moment covariance
``e_i e_j / 2 [expm1(V_ij) cos(mu_i - mu_j) - expm1(-V_ij) cos(mu_i + mu_j)]`` was evaluated as
``(e_i e_j / 2) * expm1(V_ij)``, which is ``tiny * inf`` once ``V_ij > 709.78`` and ``0 * inf``
once ``(V_ii + V_jj) / 2 > ~745``, so it was ``inf``/``nan``, and a Cholesky of a ``nan`` matrix
reports exactly that message. The inputs below are the distributions at the first failure,
recorded from the two runs (see each test); the moments are checked against Monte Carlo.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from harness.task import SaturatingCost
from plugins.pilco.controllers import LinearController, SquashedController
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.propagate import StateLayout
from plugins.pilco.trig import sin_moments, squash, squash_moments, trig_moments
from tests.pilco.random_gp import DT, mc_moments, random_posterior
from tests.pilco.test_fused_step import _reference_value_and_grad
from tests.pilco.test_trig import sin_gradients

torch.set_num_threads(1)
NUM_SAMPLES = 200_000
SIGMAS = 5.0


def _assert_mc(moments, m, S, f, gen) -> None:
    """``moments = (mean, cov, C)`` of ``f(x)``, ``x ~ N(m, S)``, within 5 MC standard errors; PSD cov."""
    mean, cov, cross = moments
    assert all(bool(torch.isfinite(t).all()) for t in moments), moments
    assert float(torch.linalg.eigvalsh(cov).min()) > 0.0
    x = m + torch.randn(NUM_SAMPLES, m.shape[0], generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T
    mc_mean, mean_se, mc_cov, cov_se, mc_cross, cross_se = mc_moments(f(x), x)
    assert torch.all((mean - mc_mean).abs() <= SIGMAS * mean_se), (mean, mc_mean)
    assert torch.all((cov - mc_cov).abs() <= SIGMAS * cov_se), (cov, mc_cov)
    assert torch.all((S @ cross - mc_cross).abs() <= SIGMAS * cross_se), (S @ cross, mc_cross)


def test_squash_moments_at_the_unicycle_failure() -> None:
    """Unicycle, trial-1 GP, a unit step along -dJ from the initial linear policy: at prediction step 7
    the controls' pre-image z has variance 89.2 (3z: 803), the control covariance was nan, and the
    GP's Cholesky failed at step 7. Now: finite, positive definite, equal to MC."""
    m = torch.tensor([-1.6549, -2.7584], dtype=DT)
    S = torch.tensor([[3.4174, 15.6243], [15.6243, 89.1807]], dtype=DT)
    u_max = torch.tensor([10.0, 50.0], dtype=DT)
    _assert_mc(squash_moments(m, S, u_max, "trapezoid"), m, S, lambda z: squash(z, u_max, "trapezoid"), torch.Generator().manual_seed(1))


def test_trig_moments_at_the_double_pendulum_failure() -> None:
    """Cart-double-pendulum, seed 0, trial 5, the kept RBF policy: at prediction step 84 the two angles
    have variances 98.8 and 733.0; [sin, cos] of them had an inf/nan covariance, and the RBF
    policy's Cholesky failed. Now: finite, positive definite, equal to MC."""
    m = torch.tensor([6.214105457344228, -0.4860774921991524], dtype=DT)
    S = torch.tensor([[98.77490194468224, 110.20663978881592], [110.20663978881592, 732.9744882632264]], dtype=DT)
    A = torch.eye(2, dtype=DT)
    f = lambda x: torch.cat([torch.sin(x), torch.cos(x)], dim=1)  # noqa: E731
    _assert_mc(trig_moments(m, S, A), m, S, f, torch.Generator().manual_seed(2))


@pytest.mark.parametrize("var", [700.0, 720.0, 760.0, 1e4, 1e8])
def test_sin_moments_across_the_overflow_threshold(var: float) -> None:
    """Closed forms for x ~ N(mu, v) and y = [x, 3x] (the trapezoid's pair), from E[cos kx] =
    exp(-k^2 v / 2) cos(k mu): var[sin x] = (1 - exp(-2v) cos 2mu) / 2 - exp(-v) sin^2 mu and
    cov[sin x, sin 3x] = (exp(-2v) cos 2mu - exp(-8v) cos 4mu) / 2 - E[sin x] E[sin 3x]."""
    mu = 0.7
    m, S = torch.tensor([mu], dtype=DT), torch.tensor([[var]], dtype=DT)
    mean, cov, cross = sin_moments(m, S, torch.tensor([[1.0], [3.0]], dtype=DT))
    e1, e3 = math.exp(-var / 2), math.exp(-9 * var / 2)
    var_sin = 0.5 * (1.0 - math.exp(-2 * var) * math.cos(2 * mu)) - e1 * e1 * math.sin(mu) ** 2
    # E[sin x sin 3x] = (E[cos 2x] - E[cos 4x]) / 2
    cov13 = 0.5 * (math.exp(-2 * var) * math.cos(2 * mu) - math.exp(-8 * var) * math.cos(4 * mu)) - e1 * e3 * math.sin(mu) * math.sin(3 * mu)
    assert bool(torch.isfinite(cov).all()) and bool(torch.isfinite(mean).all()) and bool(torch.isfinite(cross).all())
    assert math.isclose(float(cov[0, 0]), var_sin, rel_tol=1e-12)
    assert math.isclose(float(cov[0, 1]), cov13, rel_tol=1e-12, abs_tol=1e-300)
    assert math.isclose(float(mean[0]), e1 * math.sin(mu), rel_tol=1e-12, abs_tol=1e-300)


def test_hand_derived_backward_at_large_variance() -> None:
    """Gradients stay finite, equal autograd through the forward, and pass gradcheck where the old
    products overflowed (entries of A S A^T from 10 to 2000)."""
    gen = torch.Generator().manual_seed(3)
    A = torch.tensor([[1.0, 0.0], [3.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=DT)
    b = torch.tensor([0.0, 0.3, 0.5 * math.pi, 1.0], dtype=DT)
    S = torch.tensor([[90.0, 20.0], [20.0, 400.0]], dtype=DT)
    m = torch.tensor([0.4, -1.3], dtype=DT)
    weights = [torch.randn(*shape, generator=gen, dtype=DT) for shape in ((4,), (4, 4), (2, 4))]
    for hand, auto in sin_gradients(m, S, A, b, weights):
        assert bool(torch.isfinite(hand).all())
        assert torch.allclose(hand, auto, rtol=1e-12, atol=1e-14)
    # the sin(3 x_1) entry has variance 810: gradcheck in a regime with non-negligible gradients too
    small = S / 10.0
    fn = lambda mm, SS: sin_moments(mm, SS, A, b)  # noqa: E731
    for cov in (S, small):
        assert torch.autograd.gradcheck(fn, (m.clone().requires_grad_(), cov.clone().requires_grad_()))


def _wide_squash_objective() -> PolicyObjective:
    """A linear policy with two controls; the first one's pre-squash variance is 125 at t = 0
    (trapezoid: 3z has 1125 > 745), the second one's is small (informative gradients)."""
    gen = torch.Generator().manual_seed(5)
    layout = StateLayout(3, (), (0, 1, 2), (0, 2))
    weight = torch.tensor([[40.0, -30.0], [0.5, -0.7]], dtype=DT)
    ctrl = SquashedController(LinearController(weight, torch.tensor([0.2, -0.1], dtype=DT)), [2.0, 2.0])
    cost = SaturatingCost(np.zeros((0, 3)), np.array([[1.0, 0.0, 0.5]]), np.array([0.3]), 1.0)
    return PolicyObjective(ctrl, random_posterior(3, 30, 5, gen), layout, cost, [0.1, -0.2, 0.3], 0.05 * np.eye(3), 8)


def _wide_angle_objective() -> PolicyObjective:
    """An angle with variance 800 at t = 0, fed to the model and the policy as [sin, cos]."""
    gen = torch.Generator().manual_seed(6)
    layout = StateLayout.with_trig(2, [1])  # inputs [x0, sin x1, cos x1]
    ctrl = SquashedController(LinearController(torch.tensor([[0.5, -0.7, 0.3]], dtype=DT), torch.tensor([0.2], dtype=DT)), [2.0])
    cost = SaturatingCost(np.array([[0.0, 1.0]]), np.array([[1.0, 0.0, 0.0, 0.5]]), np.array([0.3]), 1.0)
    return PolicyObjective(ctrl, random_posterior(2, 30, 4, gen), layout, cost, [0.1, 2.0], np.diag([0.05, 800.0]), 8)


@pytest.mark.parametrize("make", [_wide_squash_objective, _wide_angle_objective])
def test_objective_with_huge_trig_variances(make) -> None:
    """J is finite (it raised before), the fused hand-derived gradient equals plain autograd to
    1e-10 and central finite differences to 1e-6."""
    obj = make()
    theta = obj.get_flat()
    J, grad = obj(theta)
    assert math.isfinite(J) and np.all(np.isfinite(grad))
    J_ref, grad_ref = _reference_value_and_grad(obj)
    assert abs(J - J_ref) <= 1e-12 * abs(J_ref)
    assert np.linalg.norm(grad - grad_ref) <= 1e-10 * np.linalg.norm(grad_ref)
    eps, fd = 1e-5, np.zeros_like(theta)
    for i in range(theta.size):
        step = np.zeros_like(theta)
        step[i] = eps
        fd[i] = (obj(theta + step)[0] - obj(theta - step)[0]) / (2 * eps)
    obj.set_flat(theta)
    assert np.linalg.norm(grad) > 1e-3 * abs(J)  # informative, not washed out by the wide controls
    assert np.linalg.norm(grad - fd) <= 1e-6 * np.linalg.norm(grad), (grad, fd)
