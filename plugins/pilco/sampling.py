"""Monte Carlo through the learned model: the distribution that moment matching approximates.

PILCO's J(theta) refits a Gaussian to the state distribution at every step (moment matching) and
sums the expected cost in closed form. :func:`sampled_costs` runs the *same* model and policy on
particles instead: ``x_0 ~ N(mu0, Sigma0)``; at each step every particle is augmented, the policy
(with its squashing) gives its control (from the particle plus measurement noise if the objective
plans with it), and the next state is ``x + Delta`` with ``Delta`` drawn
from the GP's predictive distribution at that particle, ``N(mean_a, var_a)`` independently per
output ``a`` (latent variance, no observation noise, as in the prediction; ``mean_only``: the
mean alone). The per-step mean cost of the particles converges to the model's own expected cost
as the particle count grows; the gap to :meth:`PolicyObjective.step_costs` is the error of the
Gaussian approximation over many steps, and the gap to a real rollout is model bias.

One step from a Gaussian state both agree to Monte Carlo error (``tests/pilco/test_sampling.py``).
Over a long horizon they can part: the particles' distribution grows heavy tails that a Gaussian
refitted at every step does not carry, and a policy search can settle where the approximation is
optimistic (``J_sampled`` beside ``J_after`` in every PILCO run's metrics shows it).
"""

from __future__ import annotations

import numpy as np
import torch

from plugins.pilco.gp import predict_latent
from plugins.pilco.objective import PolicyObjective


def sample_states(objective: PolicyObjective, particles: int, seed: int = 0) -> torch.Tensor:
    """Sampled states ``(H+1, particles, D)`` of the model's rollout (index 0: the initial samples).

    Args:
        objective: the policy objective (its controller, dynamics posterior, layout, initial
            distribution, horizon and ``mean_only`` flag are used as they are).
        particles: number of sampled trajectories.
        seed: seed of the sampling (the result is a deterministic function of it).
    """
    if particles < 1:
        raise ValueError(f"particles must be >= 1, got {particles}")
    gen = torch.Generator().manual_seed(int(seed))
    layout, posterior = objective.layout, objective.posterior
    eigval, eigvec = torch.linalg.eigh(objective.init_cov)  # a square root that also takes a singular Sigma0
    root = eigvec * eigval.clamp_min(0.0).sqrt()
    d = objective.init_mean.shape[0]
    device = objective.init_mean.device
    x = objective.init_mean + torch.randn(particles, d, generator=gen, dtype=torch.float64).to(device) @ root.T
    states = [x]
    noise_std = None if objective.policy_noise is None else objective.policy_noise.diagonal().sqrt()
    with torch.no_grad():
        for _ in range(objective.horizon):
            a = layout.augment(x)
            seen = a[:, layout.on("policy_index", device)]
            if noise_std is not None:
                seen = seen + noise_std * torch.randn(seen.shape, generator=gen, dtype=torch.float64).to(device)
            u = objective.controller(seen)
            mean, var = predict_latent(posterior, torch.cat([a[:, layout.on("model_index", device)], u], dim=1))
            x = x + mean
            if not objective.mean_only:
                x = x + var.clamp_min(0.0).sqrt() * torch.randn(x.shape, generator=gen, dtype=torch.float64).to(device)
            states.append(x)
    return torch.stack(states)


def states_costs(objective: PolicyObjective, states: torch.Tensor) -> np.ndarray:
    """Per-step expected cost ``(H,)`` of sampled states ``(H+1, particles, D)`` (:func:`sample_states`; index 0,
    the initial samples, is not charged): the mean over the particles of the objective's cost at each step."""
    with torch.no_grad():
        return objective.cost.sample(states[1:]).mean(dim=1).cpu().numpy().copy()


def sampled_costs(objective: PolicyObjective, particles: int, seed: int = 0) -> np.ndarray:
    """Per-step expected cost ``(H,)`` for ``x_1 .. x_H`` by :func:`sample_states` (the task's cost
    with the objective's width); the Monte Carlo error of each step is at most ``0.5 / sqrt(particles)``."""
    return states_costs(objective, sample_states(objective, particles, seed))
