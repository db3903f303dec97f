"""Policy evaluation by particles through the GP model (MC-PILCO: Amadio et al., IEEE T-RO 2022).

PILCO evaluates a policy by moment matching: a Gaussian refitted to the state distribution at every
step, the expected cost in closed form. MC-PILCO keeps the same GP model and the same controllers
but estimates the expected cost with ``N`` particles, and differentiates the estimate::

    x_0^i ~ N(mu0, Sigma0)                                   i = 1..N
    u_t^i = pi_theta(a(x_t^i)[policy_inputs]; dropout mask m^i)
    Delta^i ~ N(mean(z^i), var(z^i)),  z^i = [a(x_t^i)[model_inputs], u_t^i]   (per output, independently)
    x_{t+1}^i = x_t^i + mean(z^i) + sqrt(var(z^i)) eps^i      (reparameterisation: eps^i ~ N(0, I) fixed)
    J_hat(theta) = sum_{t=1..H} 1/N sum_i c(x_t^i)

``mean`` and ``var`` are the GP's predictive mean and latent variance at a deterministic input
(:func:`plugins.pilco.gp.predict_latent`, as :mod:`plugins.pilco.sampling` does without
gradients). Every quantity is a differentiable function of ``theta`` once the noise ``eps`` (and the
dropout masks) are drawn, so autograd gives an unbiased estimate of dJ/dtheta.

Dropout (the paper's regulariser and exploration device): with probability ``p`` each RBF weight of
each particle's policy is set to 0, the others scaled by ``1/(1-p)``; the RBF weights are the GP-mean
weights ``beta`` of :class:`~plugins.pilco.controllers.RBFController`. Linear policies get no dropout.

Shapes: ``N`` particles, ``D`` state dimensions, ``F`` controls, ``n_c`` RBF centres, ``H`` steps.
Cost per step: one GP prediction at ``N`` inputs, ``O(E N n^2)`` for the variances (``n`` basis points).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from plugins.pilco.controllers import RBFController, SquashedController
from plugins.pilco.cost import CostMoments
from plugins.pilco.gp import predict_latent
from plugins.pilco.kernels import se_ard
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.propagate import StateLayout
from plugins.pilco.trig import squash

#: variances are floored here before the square root (its gradient at 0 is infinite)
VAR_FLOOR = 1e-12


def policy_actions(controller: torch.nn.Module, inputs: torch.Tensor, dropout: float = 0.0,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """Controls ``(N, F)`` for policy inputs ``(N, p)``, each particle with its own dropout mask on the
    RBF weights (probability ``dropout``; none for linear policies or ``dropout = 0``). ``controller``:
    a :class:`~plugins.pilco.controllers.SquashedController` or a bare (unsquashed) controller."""
    squashed = isinstance(controller, SquashedController)
    base = controller.base if squashed else controller
    if isinstance(base, RBFController) and dropout > 0.0:
        post = base.posterior()
        k = se_ard(inputs, post.inputs, post.log_ell, post.log_alpha)  # (F, N, n_c)
        keep = (torch.rand(k.shape, generator=generator, dtype=k.dtype, device="cpu") >= dropout).to(k.device)
        z = torch.einsum("anm,am->na", k * keep / (1.0 - dropout), post.beta)
    else:
        z = base(inputs)
    return squash(z, controller.u_max, controller.kind) if squashed and controller.kind is not None else z


@dataclass
class ParticleObjective:
    """``J_hat(theta)``: the particle estimate of the expected cost of the controller's policy.

    Args:
        controller: the policy; its parameters are theta.
        posterior: the dynamics GP (``E = D`` outputs, inputs ``[a[model_inputs], u]``), detached.
        layout: the state layout shared with PILCO.
        cost: the planning cost (the task's cost with the planning width).
        init_mean, init_cov: ``(D,)``, ``(D, D)``.
        horizon: predicted and costed steps ``H``.
        particles: ``N``.
    """

    controller: torch.nn.Module
    posterior: GPPosterior
    layout: StateLayout
    cost: CostMoments
    init_mean: torch.Tensor
    init_cov: torch.Tensor
    horizon: int
    particles: int

    def __post_init__(self) -> None:
        if self.particles < 1:
            raise ValueError(f"particles must be >= 1, got {self.particles}")
        eigval, eigvec = torch.linalg.eigh(self.init_cov)  # a square root that also takes a singular Sigma0
        self._root = eigvec * eigval.clamp_min(0.0).sqrt()

    def rollout(self, generator: torch.Generator, dropout: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Sampled states ``(H+1, N, D)`` and the per-step mean cost ``(H,)`` of ``x_1..x_H``, both
        differentiable wrt the controller's parameters; ``generator`` (a CPU generator) draws the
        initial states, the model's noise and the dropout masks. The objective computes where its
        tensors are (``init_mean``'s device: the posterior, controller and cost must be there too); the
        random numbers are drawn on the CPU and copied, so a GPU gets the same ones as the CPU."""
        d, device = self.init_mean.shape[0], self.init_mean.device
        draw = torch.randn(self.particles, d, generator=generator, dtype=torch.float64, device="cpu").to(device)
        x = self.init_mean + draw @ self._root.T
        layout = self.layout
        policy_index, model_index = layout.on("policy_index", device), layout.on("model_index", device)
        states, costs = [x], []
        for _ in range(self.horizon):
            a = layout.augment(x)
            u = policy_actions(self.controller, a[:, policy_index], dropout, generator)
            mean, var = predict_latent(self.posterior, torch.cat([a[:, model_index], u], dim=1))
            eps = torch.randn(x.shape, generator=generator, dtype=torch.float64, device="cpu").to(device)
            x = x + mean + var.clamp_min(VAR_FLOOR).sqrt() * eps
            states.append(x)
            costs.append(self.cost.sample(x).mean())
        return torch.stack(states), torch.stack(costs)

    def value(self, generator: torch.Generator, dropout: float = 0.0) -> torch.Tensor:
        """``J_hat`` (a differentiable scalar)."""
        return self.rollout(generator, dropout)[1].sum()
