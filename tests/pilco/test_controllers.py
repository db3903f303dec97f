"""RBF and linear controllers, with squashing (plugins.pilco.controllers), vs independent computations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.pilco.controllers import LinearController, RBFController, SquashedController
from tests.pilco.random_gp import DT, mc_moments, random_gaussian

torch.set_num_threads(1)
NUM_SAMPLES = 100_000
SIGMAS = 5.0


def _samples(m, S, gen):
    return m + torch.randn(NUM_SAMPLES, m.shape[0], generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T


def _assert_mc(moments, m, S, x, u):
    M, V, C = moments
    mean, mean_se, cov, cov_se, cross, cross_se = mc_moments(u, x)
    assert torch.all((M - mean).abs() <= SIGMAS * mean_se + 1e-12), (M, mean)
    assert torch.all((V - cov).abs() <= SIGMAS * cov_se + 1e-12), (V, cov)
    assert torch.all((S @ C - cross).abs() <= SIGMAS * cross_se + 1e-12), (S @ C, cross)


def _rbf(num_centres=12, p=3, F=2, seed=0) -> RBFController:
    gen = torch.Generator().manual_seed(seed)
    m, S = torch.zeros(p, dtype=DT), torch.eye(p, dtype=DT)
    ctrl = RBFController.initial(m, S, num_centres, F, torch.full((p,), 0.8, dtype=DT), gen)
    with torch.no_grad():  # targets of order 1 so that the output is far from linear
        ctrl.targets.mul_(10.0)
    return ctrl


def test_parameter_count_matches_paper() -> None:
    """Cart-pole: 50 centres, 5 policy inputs, 1 control -> theta in R^305 (ICML 2011, Table 1)."""
    ctrl = RBFController.initial(torch.zeros(5, dtype=DT), torch.eye(5, dtype=DT), 50, 1, torch.ones(5, dtype=DT))
    assert sum(p.numel() for p in ctrl.parameters()) == 305
    assert sum(p.numel() for p in SquashedController(ctrl, [10.0]).parameters()) == 305
    lin = LinearController.initial(12, 2)
    assert sum(p.numel() for p in lin.parameters()) == 26


def test_rbf_forward_is_the_regularised_rbf_network() -> None:
    """z_a(x) = sum_i beta_ai exp(-1/2 |(x - c_i)/ell_a|^2), beta_a = (K_a + 0.01^2 I)^-1 t_a (numpy)."""
    ctrl = _rbf()
    c = ctrl.centres.detach().numpy()
    t = ctrl.targets.detach().numpy()
    ell = np.exp(ctrl.log_ell.detach().numpy())
    x = np.random.default_rng(0).standard_normal((7, 3))
    expected = np.zeros((7, 2))
    for a in range(2):
        d = (c[:, None, :] - c[None, :, :]) / ell[a]
        K = np.exp(-0.5 * (d**2).sum(-1)) + 1e-4 * np.eye(len(c))
        beta = np.linalg.solve(K, t[:, a])
        kx = np.exp(-0.5 * (((x[:, None, :] - c[None]) / ell[a]) ** 2).sum(-1))
        expected[:, a] = kx @ beta
    got = ctrl(torch.as_tensor(x)).detach().numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-10)
    # targets are (nearly) interpolated at the centres
    np.testing.assert_allclose(ctrl(ctrl.centres).detach().numpy(), t, atol=0.05 * np.abs(t).max())


def test_rbf_initialisation_statistics() -> None:
    gen = torch.Generator().manual_seed(3)
    mean = torch.tensor([1.0, -2.0], dtype=DT)
    cov = torch.tensor([[0.04, 0.01], [0.01, 0.09]], dtype=DT)
    ctrl = RBFController.initial(mean, cov, 20_000, 1, torch.tensor([1.0, 0.7], dtype=DT), gen)
    c = ctrl.centres.detach()
    assert torch.allclose(c.mean(0), mean, atol=0.01)
    assert torch.allclose(torch.cov(c.T), cov, atol=0.005)
    assert abs(float(ctrl.targets.detach().std()) - 0.1) < 0.005
    assert torch.allclose(torch.exp(ctrl.log_ell), torch.tensor([[1.0, 0.7]], dtype=DT))


def test_rbf_moments_match_monte_carlo() -> None:
    gen = torch.Generator().manual_seed(4)
    ctrl = _rbf()
    m, S = random_gaussian(3, gen, scale=0.9)
    x = _samples(m, S, gen)
    with torch.no_grad():
        u = ctrl(x)
        _assert_mc(ctrl.moment_map()(m, S), m, S, x, u)


def test_linear_moments_match_monte_carlo() -> None:
    gen = torch.Generator().manual_seed(5)
    ctrl = LinearController(torch.randn(2, 4, generator=gen, dtype=DT), torch.randn(2, generator=gen, dtype=DT))
    m, S = random_gaussian(4, gen)
    x = _samples(m, S, gen)
    with torch.no_grad():
        _assert_mc(ctrl.moment_map()(m, S), m, S, x, ctrl(x))


@pytest.mark.parametrize("kind", ["trapezoid", "sin"])
def test_squashed_linear_matches_monte_carlo(kind: str) -> None:
    """Linear then squash: z is exactly Gaussian, so the chained moments are exact."""
    gen = torch.Generator().manual_seed(6)
    base = LinearController(torch.randn(2, 3, generator=gen, dtype=DT), torch.randn(2, generator=gen, dtype=DT))
    ctrl = SquashedController(base, [10.0, 3.0], kind)
    m, S = random_gaussian(3, gen, scale=1.0)
    x = _samples(m, S, gen)
    with torch.no_grad():
        u = ctrl(x)
        assert torch.all(u.abs() <= torch.tensor([10.0, 3.0], dtype=DT) + 1e-12)
        _assert_mc(ctrl.moment_map()(m, S), m, S, x, u)


def test_squashed_rbf_chains_cross_covariance() -> None:
    """RBF + squash: C = C_rbf @ C_squash; MC of squash(z), z ~ N(M_z, V_z) jointly with x."""
    gen = torch.Generator().manual_seed(7)
    base = _rbf(F=1)
    ctrl = SquashedController(base, [5.0])
    m, S = random_gaussian(3, gen, scale=0.3)
    with torch.no_grad():
        mz, vz, cz = base.moment_map()(m, S)
        M, V, C = ctrl.moment_map()(m, S)
        # the Gaussian (x, z) that moment matching assumes, then the exact nonlinearity
        joint_cov = torch.cat([torch.cat([S, S @ cz], 1), torch.cat([(S @ cz).T, vz], 1)], 0)
        xz = _samples(torch.cat([m, mz]), joint_cov, gen)
        u = ctrl.u_max * (9 * torch.sin(xz[:, 3:]) + torch.sin(3 * xz[:, 3:])) / 8
        _assert_mc((M, V, C), m, S, xz[:, :3], u)
        # and the true (non-Gaussian) propagation is close for this moderate input spread
        x = _samples(m, S, gen)
        assert torch.allclose(M, ctrl(x).mean(0), atol=0.05 * 5.0)


def test_squash_validation() -> None:
    with pytest.raises(ValueError):
        SquashedController(LinearController.initial(2, 1), [1.0], "tanh")
    with pytest.raises(ValueError):
        SquashedController(LinearController.initial(2, 1), [1.0, 2.0])
