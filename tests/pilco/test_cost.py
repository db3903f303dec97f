"""Expected saturating cost (plugins.pilco.cost) vs Monte Carlo, lossSat's a-space formula and the
harness's own cost function (1/2-width convention)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.task import SaturatingCost
from plugins.pilco.cost import CostMoments, gaussian_saturation
from plugins.pilco.trig import augment_trig
from tests.pilco.random_gp import DT, random_gaussian

torch.set_num_threads(1)
NUM_SAMPLES = 400_000
SIGMAS = 5.0
POLE = 0.5


def cartpole_cost(width: float = 0.25) -> SaturatingCost:
    """Pole-tip distance from upright: r = [x + l sin(theta), -l cos(theta) - l], x = [x, xdot, thetadot, theta]."""
    return SaturatingCost(
        angle_map=np.array([[0.0, 0.0, 0.0, 1.0]]),
        linear_map=np.array([[1.0, 0, 0, 0, POLE, 0], [0, 0, 0, 0, 0, -POLE]]),
        target=np.array([0.0, POLE]),
        width=width,
    )


def _mc_mean_var(c: torch.Tensor):
    n = c.shape[0]
    mean = c.mean()
    sq = (c - mean) ** 2
    return mean, c.std() / n**0.5, sq.mean(), sq.std() / n**0.5


@pytest.mark.parametrize("width", [0.25, 1.0])
def test_gaussian_saturation_matches_monte_carlo(width: float) -> None:
    gen = torch.Generator().manual_seed(1)
    m, S = random_gaussian(2, gen, scale=0.5)
    r = m + torch.randn(NUM_SAMPLES, 2, generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T
    c = 1 - torch.exp(-(r * r).sum(1) / (2 * width**2))
    mean, mean_se, var, var_se = _mc_mean_var(c)
    e, v = gaussian_saturation(m, S, width)
    assert abs(e - mean) <= SIGMAS * mean_se
    assert abs(v - var) <= SIGMAS * var_se


def test_cost_without_angles_is_exact() -> None:
    """K = 0: a(x) = x is Gaussian, so E[c] and Var[c] are exact; MC over x."""
    gen = torch.Generator().manual_seed(2)
    cost = SaturatingCost(np.zeros((0, 3)), np.array([[1.0, 0.5, 0.0], [0.0, 1.0, -1.0]]), np.array([0.2, -0.1]), 0.7)
    m, S = random_gaussian(3, gen, scale=0.6)
    x = m + torch.randn(NUM_SAMPLES, 3, generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T
    c = torch.as_tensor(cost(x.numpy()))
    mean, mean_se, var, var_se = _mc_mean_var(c)
    e, v = CostMoments(cost)(m, S)
    assert abs(e - mean) <= SIGMAS * mean_se
    assert abs(v - var) <= SIGMAS * var_se


def test_equals_losssat_in_feature_space() -> None:
    """Reference lossSat on a = [x, sin, cos]: W = C^T C / w^2, z with C z = target."""
    gen = torch.Generator().manual_seed(3)
    cost = cartpole_cost()
    m, S = random_gaussian(4, gen, scale=0.4)
    ma, Sa = augment_trig(m, S, torch.as_tensor(cost.angle_map))
    ma, Sa = ma.numpy(), Sa.numpy()
    W = cost.weight
    z = np.linalg.lstsq(cost.linear_map, cost.target, rcond=None)[0]
    I = np.eye(len(ma))
    d = ma - z
    SW = Sa @ W
    e_ref = 1 - np.linalg.det(I + SW) ** -0.5 * np.exp(-0.5 * d @ W @ np.linalg.solve(I + SW, d))
    second = np.linalg.det(I + 2 * SW) ** -0.5 * np.exp(-d @ W @ np.linalg.solve(I + 2 * SW, d))
    v_ref = second - (1 - e_ref) ** 2
    e, v = CostMoments(cost)(torch.as_tensor(m), torch.as_tensor(S))
    assert abs(float(e) - e_ref) < 1e-12
    assert abs(float(v) - v_ref) < 1e-12


def test_deterministic_limit_is_the_harness_cost() -> None:
    """S -> 0 gives c(m) exactly as the environment computes it (same 1/2-width convention)."""
    cost = cartpole_cost()
    for state in ([0.1, 0.0, 0.0, 3.0], [0.0, 1.0, -2.0, np.pi], [0.3, 0.0, 0.0, 0.2]):
        e, v = CostMoments(cost)(torch.tensor(state, dtype=DT), 1e-14 * torch.eye(4, dtype=DT))
        assert abs(float(e) - float(cost(np.array(state)))) < 1e-10
        assert float(v) < 1e-10


def test_cartpole_cost_close_to_true_expectation() -> None:
    """With angles the a(x) Gaussian is an approximation; for a modest spread it is accurate."""
    gen = torch.Generator().manual_seed(4)
    cost = cartpole_cost()
    m = torch.tensor([0.1, 0.0, 0.0, 2.9], dtype=DT)
    S = torch.diag(torch.tensor([0.05, 0.1, 0.1, 0.1], dtype=DT)) ** 2
    x = m + torch.randn(NUM_SAMPLES, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T
    c = torch.as_tensor(cost(x.numpy()))
    e, v = CostMoments(cost)(m, S)
    assert abs(float(e) - float(c.mean())) < 0.01
    assert abs(float(v) - float(c.var())) < 0.01


def test_batched_and_width_override() -> None:
    gen = torch.Generator().manual_seed(5)
    pairs = [random_gaussian(4, gen, 0.3) for _ in range(3)]
    ms, Ss = torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])
    cm = CostMoments(cartpole_cost(), width=0.5)
    eb, vb = cm(ms, Ss)
    assert eb.shape == (3,) and vb.shape == (3,)
    ref = CostMoments(cartpole_cost(0.5))
    for i, (m, S) in enumerate(pairs):
        e, v = ref(m, S)
        assert torch.allclose(eb[i], e, atol=1e-15) and torch.allclose(vb[i], v, atol=1e-15)


def test_degenerate_covariance_is_a_numerical_error_naming_the_step() -> None:
    """A propagated covariance that lost definiteness (or became NaN) raises the harness's
    NumericalError, which the policy search counts as +inf, instead of a bare LinAlgError."""
    from harness.errors import NumericalError

    m = torch.zeros(3, 2, dtype=torch.float64)
    S = torch.eye(2, dtype=torch.float64).repeat(3, 1, 1) * 0.01
    S[2, 0, 0] = -1.0
    with pytest.raises(NumericalError, match=r"prediction step\(s\) \[2\]"):
        gaussian_saturation(m, S, 0.25)
    S[2, 0, 0] = float("nan")
    with pytest.raises(NumericalError):
        gaussian_saturation(m, S, 0.25)
