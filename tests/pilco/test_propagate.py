"""One-step propagation and rollouts (plugins.pilco.propagate) vs Monte Carlo and exact limits.

MC of one step: x ~ N(m, S); a = [x, sin, cos]; u = policy(a[policy_inputs]) exactly; Delta ~
N(GP mean, GP latent variance) at [a[model_inputs], u]; x' = x + Delta.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.pilco.controllers import LinearController, RBFController, SquashedController
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.propagate import StateLayout, act, propagate_step, rollout
from tests.pilco.random_gp import DT, gp_mean_var, mc_moments, pendulum_posterior, random_gaussian, random_posterior

torch.set_num_threads(1)
NUM_SAMPLES = 100_000
SIGMAS = 5.0


def _mc_step(m, S, post, ctrl, layout, gen, num_samples=NUM_SAMPLES):
    x = m + torch.randn(num_samples, m.shape[0], generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T
    with torch.no_grad():
        a = layout.augment(x)
        u = ctrl(a[:, layout.policy_index])
        f, var = gp_mean_var(post, torch.cat([a[:, layout.model_index], u], dim=1))
    delta = f + var.clamp_min(0).sqrt() * torch.randn(f.shape, generator=gen, dtype=DT)
    return x + delta


def _pendulum_setup(seed: int):
    gen = torch.Generator().manual_seed(seed)
    post = pendulum_posterior(150, gen)
    layout = StateLayout.with_trig(2, [1])
    base = RBFController.initial(torch.tensor([0.0, 0.0, -1.0], dtype=DT), 0.3 * torch.eye(3, dtype=DT), 10, 1, torch.ones(3, dtype=DT), gen)
    with torch.no_grad():
        base.targets.mul_(10.0)
    return gen, post, layout, SquashedController(base, [2.0])


def test_layout_with_trig_cartpole() -> None:
    layout = StateLayout.with_trig(4, [3])
    assert layout.model_inputs == (0, 1, 2, 4, 5) and layout.policy_inputs == (0, 1, 2, 4, 5)
    assert layout.augmented_dim == 6
    x = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=DT)
    assert torch.allclose(layout.augment(x), torch.tensor([0.1, 0.2, 0.3, 0.4, np.sin(0.4), np.cos(0.4)], dtype=DT))
    with pytest.raises(ValueError):
        StateLayout(4, (3,), (0, 6), (0,))
    with pytest.raises(ValueError):
        StateLayout(4, (4,), (0,), (0,))


def test_exact_case_matches_monte_carlo() -> None:
    """No angles, unsquashed linear policy: the joint (x, u) is Gaussian, so the step is exact.
    (4e5 samples: a 10 % error in cov[x, u] is then about 10 standard errors.)"""
    gen = torch.Generator().manual_seed(1)
    post = random_posterior(3, 25, 4, gen)
    layout = StateLayout(3, (), (0, 1, 2), (0, 2))
    ctrl = LinearController(torch.tensor([[0.5, -0.7]], dtype=DT), torch.tensor([0.2], dtype=DT))
    m, S = random_gaussian(3, gen, scale=0.6)
    m1, S1 = propagate_step(m, S, MomentMatchingGP(post), ctrl.moment_map(), layout)
    x1 = _mc_step(m, S, post, ctrl, layout, gen, num_samples=400_000)
    mean, mean_se, cov, cov_se, _, _ = mc_moments(x1, x1)
    assert torch.all((m1 - mean).abs() <= SIGMAS * mean_se)
    assert torch.all((S1 - cov).abs() <= SIGMAS * cov_se)


def test_pendulum_step_close_to_monte_carlo() -> None:
    """Angle augmentation + RBF + squash (Gaussian approximations at each stage): close to MC, and
    far closer than the same step without the cross-covariance terms (eq. 11)."""
    gen, post, layout, ctrl = _pendulum_setup(2)
    m = torch.tensor([0.5, 2.5], dtype=DT)
    S = torch.tensor([[0.04, 0.01], [0.01, 0.03]], dtype=DT)
    m1, S1 = propagate_step(m, S, MomentMatchingGP(post), ctrl.moment_map(), layout)
    x1 = _mc_step(m, S, post, ctrl, layout, gen)
    mean, mean_se, cov, cov_se, _, _ = mc_moments(x1, x1)
    tol_m = SIGMAS * mean_se + 0.002 * mean.abs().max()
    tol_S = SIGMAS * cov_se + 0.01 * cov.abs().max()
    assert torch.all((m1 - mean).abs() <= tol_m), (m1, mean)
    assert torch.all((S1 - cov).abs() <= tol_S), (S1, cov)
    # the test can fail: dropping cov[x, Delta] (S' = S + V_Delta) is detected
    md, vd, _ = MomentMatchingGP(post).predict(*_gp_input_moments(m, S, layout, ctrl))
    assert not torch.all((S + vd - cov).abs() <= tol_S)


def _gp_input_moments(m, S, layout, ctrl):
    from plugins.pilco.trig import augment_trig

    ma, sa = augment_trig(m, S, layout.angle_map)
    pol, mod = layout.policy_index, layout.model_index
    mu, su, cu = ctrl.moment_map()(ma[pol], sa[pol[:, None], pol[None, :]])
    s_au = sa[:, pol] @ cu
    m_in = torch.cat([ma[mod], mu])
    s_in = torch.cat([torch.cat([sa[mod][:, mod], s_au[mod]], 1), torch.cat([s_au[mod].T, su], 1)], 0)
    return m_in, s_in


def test_deterministic_limit_follows_the_gp_mean() -> None:
    """S -> 0: m' = m + GP mean at [a(m)[model_inputs], act(m)] (indices and chaining)."""
    _, post, layout, ctrl = _pendulum_setup(3)
    m = torch.tensor([-0.7, 1.3], dtype=DT)
    m1, S1 = propagate_step(m, 1e-12 * torch.eye(2, dtype=DT), MomentMatchingGP(post), ctrl.moment_map(), layout)
    u = torch.as_tensor(act(m.numpy(), ctrl, layout))
    a = layout.augment(m)
    f, var = gp_mean_var(post, torch.cat([a[layout.model_index], u])[None])
    assert torch.allclose(m1, m + f[0], atol=1e-8)
    assert torch.allclose(S1, torch.diag(var[0]), atol=1e-8)


def test_act_is_controller_on_augmented_state() -> None:
    _, _, layout, ctrl = _pendulum_setup(4)
    x = np.array([0.3, -2.0])
    u = act(x, ctrl, layout)
    z = ctrl.base(torch.tensor([[0.3, np.sin(-2.0), np.cos(-2.0)]], dtype=DT))
    expected = 2.0 * (9 * torch.sin(z) + torch.sin(3 * z)) / 8
    assert u.shape == (1,) and np.allclose(u, expected.detach().numpy()[0], atol=1e-12)


def test_rollout_shapes_and_psd() -> None:
    _, post, layout, ctrl = _pendulum_setup(5)
    m0 = torch.tensor([0.0, 0.0], dtype=DT)
    S0 = 0.01 * torch.eye(2, dtype=DT)
    means, covs = rollout(m0, S0, 15, post, ctrl, layout)
    assert means.shape == (16, 2) and covs.shape == (16, 2, 2)
    assert torch.equal(means[0], m0) and torch.equal(covs[0], S0)
    assert torch.allclose(covs, covs.mT, atol=0)
    assert torch.all(torch.linalg.eigvalsh(covs) > -1e-12)
    with pytest.raises(ValueError):
        rollout(m0, S0, 3, post, ctrl, StateLayout(2, (), (0, 1), (0, 1)))


def test_mean_only_ablation_is_overconfident_away_from_data() -> None:
    """The deterministic-GP-mean ablation ignores model uncertainty: far from the data its
    propagated variances are smaller (one step: the difference is exactly diag(E[var_f]) >= 0)."""
    gen, post, layout, ctrl = _pendulum_setup(6)
    m = torch.tensor([10.0, 0.5], dtype=DT)  # thetadot = 10 rad/s; data in [-3, 3], length-scale 3
    S = 0.01 * torch.eye(2, dtype=DT)
    dyn = MomentMatchingGP(post)
    _, S_full = propagate_step(m, S, dyn, ctrl.moment_map(), layout)
    _, S_mean = propagate_step(m, S, dyn, ctrl.moment_map(), layout, mean_only=True)
    diff = S_full - S_mean
    assert torch.allclose(diff, torch.diag(torch.diagonal(diff)), atol=1e-14)
    assert torch.all(torch.diagonal(diff) > 0.5 * torch.exp(2 * post.log_alpha))  # mostly prior variance
    _, covs_full = rollout(m, S, 10, post, ctrl, layout)
    _, covs_mean = rollout(m, S, 10, post, ctrl, layout, mean_only=True)
    var_full = torch.diagonal(covs_full, dim1=-2, dim2=-1)[1:]
    var_mean = torch.diagonal(covs_mean, dim1=-2, dim2=-1)[1:]
    assert torch.all(var_full > var_mean)
