"""Monte Carlo through the model (plugins.pilco.sampling) against the closed-form prediction."""

from __future__ import annotations

import numpy as np
import torch

from plugins.pilco.controllers import LinearController, SquashedController
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.propagate import StateLayout
from plugins.pilco.sampling import sample_states, sampled_costs
from harness.task import SaturatingCost
from tests.pilco.random_gp import DT, pendulum_posterior, random_posterior
from tests.pilco.test_objective import pendulum_cost

torch.set_num_threads(1)


def _objective(init_std: float, horizon: int, mean_only: bool = False, gain: float = 0.3) -> PolicyObjective:
    post = pendulum_posterior(80, torch.Generator().manual_seed(11))
    base = LinearController(torch.tensor([[gain, -gain, 0.2 * gain]], dtype=DT), torch.tensor([0.1], dtype=DT))
    return PolicyObjective(SquashedController(base, [2.0]), post, StateLayout.with_trig(2, [1]), pendulum_cost(),
                           [0.0, 0.8], np.diag([init_std, init_std]) ** 2, horizon, mean_only=mean_only)


def test_a_point_start_gives_the_closed_form_trajectory():
    """With (almost) no initial spread and the model variance dropped, every particle follows the
    deterministic trajectory: the sampled cost equals the closed form's cost at each step."""
    obj = _objective(1e-9, horizon=6, mean_only=True)
    with torch.no_grad():
        closed = obj.step_costs()[0].numpy()
    np.testing.assert_allclose(sampled_costs(obj, particles=3, seed=1), closed, rtol=1e-6, atol=1e-9)


def test_one_step_moments_match_moment_matching():
    """One step from a Gaussian with a nearly linear policy: moment matching gives the exact mean
    and covariance of the model's predictive distribution; 200k particles agree to MC error."""
    obj = _objective(0.15, horizon=1, gain=0.05)
    with torch.no_grad():
        means, covs = obj.state_distributions()
    x1 = sample_states(obj, 200_000, seed=2)[1]
    sd = covs[1].diagonal().sqrt()
    np.testing.assert_allclose(((x1.mean(0) - means[1]) / sd).numpy(), 0.0, atol=0.01)
    np.testing.assert_allclose((torch.cov(x1.T) / (sd[:, None] * sd[None, :])).numpy(),
                               (covs[1] / (sd[:, None] * sd[None, :])).numpy(), atol=0.015)


def test_one_step_moments_with_measurement_noise_on_the_policy_input():
    """A policy acting on noisy observations (``policy_noise_std``): with a linear policy the state
    and control are exactly jointly Gaussian, so one moment-matching step is exact, and 200k
    particles (each control from the particle plus its own noise draw) agree to MC error. The noise
    moves the prediction, so the check has teeth."""
    gen = torch.Generator().manual_seed(8)
    post = random_posterior(3, 30, 4, gen)
    layout = StateLayout(3, (), (0, 1, 2), (0, 2))
    cost = SaturatingCost(np.zeros((0, 3)), np.array([[1.0, 0.0, 0.5]]), np.array([0.3]), 1.0)
    ctrl = LinearController(torch.tensor([[1.5, -1.0]], dtype=DT), torch.tensor([0.2], dtype=DT))
    moments = []
    for noise in ([0.4, 0.0, 0.3], None):
        obj = PolicyObjective(ctrl, post, layout, cost, [0.1, -0.2, 0.3], 0.02 * np.eye(3), 1, policy_noise_std=noise)
        with torch.no_grad():
            means, covs = obj.state_distributions()
        moments.append((means[1], covs[1]))
        if noise is not None:
            x1 = sample_states(obj, 200_000, seed=5)[1]
            sd = covs[1].diagonal().sqrt()
            np.testing.assert_allclose(((x1.mean(0) - means[1]) / sd).numpy(), 0.0, atol=0.01)
            np.testing.assert_allclose((torch.cov(x1.T) / (sd[:, None] * sd[None, :])).numpy(),
                                       (covs[1] / (sd[:, None] * sd[None, :])).numpy(), atol=0.015)
    (m_noisy, S_noisy), (m_clean, S_clean) = moments
    assert float((S_noisy.diagonal() / S_clean.diagonal()).max()) > 1.2


def test_from_a_point_the_spread_is_the_models_predictive_variance():
    """From a point start, one step spreads the particles by the GP's latent variance at that
    point, which is the whole of the closed form's covariance there (to 0.5 % with 200k particles)."""
    obj = _objective(1e-9, horizon=1)
    with torch.no_grad():
        means, covs = obj.state_distributions()
    x1 = sample_states(obj, 200_000, seed=3)[1]
    np.testing.assert_allclose((x1.var(0) / covs[1].diagonal()).numpy(), 1.0, atol=0.015)
    np.testing.assert_allclose(x1.mean(0).numpy(), means[1].numpy(), atol=3e-3 * float(covs[1].diagonal().sqrt().max()))
    assert float(sample_states(_objective(1e-9, horizon=1, mean_only=True), 100, seed=3)[1].var(0).max()) < 1e-15


def test_sampling_is_seeded():
    obj = _objective(0.15, horizon=5)
    a, b, c = (sampled_costs(obj, 64, seed=s) for s in (4, 4, 5))
    assert np.array_equal(a, b) and not np.array_equal(a, c) and a.shape == (5,)


def test_cost_on_samples_is_the_tasks_cost():
    obj = _objective(0.15, horizon=1)
    x = torch.randn(50, 2, generator=torch.Generator().manual_seed(3), dtype=DT)
    np.testing.assert_allclose(obj.cost.sample(x).numpy(), pendulum_cost()(x.numpy()), rtol=1e-12)
