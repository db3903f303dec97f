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

import math
from dataclasses import dataclass, field

import torch

from plugins.mc_pilco.costs import StateCost
from plugins.pilco.controllers import RBFController, SquashedController
from plugins.pilco.cost import CostMoments
from plugins.pilco.gp import predict_latent
from plugins.pilco.kernels import any_failed, capture_cuda_graph, capture_failure, deferred_checks, se_ard
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.propagate import StateLayout
from plugins.pilco.trig import squash

#: variances are floored here before the square root (its gradient at 0 is infinite)
VAR_FLOOR = 1e-12


def policy_actions(controller: torch.nn.Module, inputs: torch.Tensor, dropout: float = 0.0,
                   generator: torch.Generator | None = None, keep: torch.Tensor | None = None,
                   posterior: GPPosterior | None = None) -> torch.Tensor:
    """Controls ``(N, F)`` for policy inputs ``(N, p)``, each particle with its own dropout mask on the
    RBF weights (probability ``dropout``; none for linear policies or ``dropout = 0``). ``controller``:
    a :class:`~plugins.pilco.controllers.SquashedController` or a bare (unsquashed) controller.

    The mask is ``keep`` (bool ``(F, N, n_c)``, drawn by :func:`dropout_shape`'s caller) if given,
    else drawn here from ``generator`` on the CPU. ``posterior``: the RBF network's
    :meth:`~plugins.pilco.controllers.RBFController.posterior`, if the caller already formed it (it
    depends on the parameters only, so a rollout forms it once instead of once per step)."""
    squashed = isinstance(controller, SquashedController)
    base = controller.base if squashed else controller
    if isinstance(base, RBFController) and dropout > 0.0:
        post = base.posterior() if posterior is None else posterior
        k = se_ard(inputs, post.inputs, post.log_ell, post.log_alpha)  # (F, N, n_c)
        if keep is None:
            keep = (torch.rand(k.shape, generator=generator, dtype=k.dtype, device="cpu") >= dropout).to(k.device)
        z = torch.einsum("anm,am->na", k * keep / (1.0 - dropout), post.beta)
    elif isinstance(base, RBFController) and posterior is not None:
        k = se_ard(inputs, posterior.inputs, posterior.log_ell, posterior.log_alpha)  # as RBFController.forward
        z = torch.einsum("anm,am->na", k, posterior.beta)
    else:
        z = base(inputs)
    return squash(z, controller.u_max, controller.kind) if squashed and controller.kind is not None else z


def dropout_shape(controller: torch.nn.Module, particles: int, dropout: float) -> tuple[int, int, int] | None:
    """``(F, N, n_c)``: the shape of one step's dropout mask, or ``None`` where no mask is drawn (a linear
    policy, or ``dropout = 0``)."""
    base = controller.base if isinstance(controller, SquashedController) else controller
    if isinstance(base, RBFController) and dropout > 0.0:
        return (base.num_controls, particles, base.centres.shape[0])
    return None


@dataclass
class ParticleDraws:
    """The random numbers of one rollout, drawn on the CPU in the order the rollout uses them (the
    initial states, then per step the dropout mask and the model's noise), so that drawing them all
    first gives the same numbers as drawing each where it is used.

    Attributes:
        init: ``(N, D)`` standard normal draws of the initial states.
        noise: ``(H, N, D)`` standard normal draws of the model's noise, per step.
        keep: ``(H, F, N, n_c)`` bool dropout masks per step, or ``None`` (no dropout).
    """

    init: torch.Tensor
    noise: torch.Tensor
    keep: torch.Tensor | None

    def to(self, device: torch.device) -> ParticleDraws:
        """The same numbers on ``device`` (one copy per tensor)."""
        return ParticleDraws(self.init.to(device), self.noise.to(device), None if self.keep is None else self.keep.to(device))


@dataclass
class ParticleObjective:
    """``J_hat(theta)``: the particle estimate of the expected cost of the controller's policy.

    Args:
        controller: the policy; its parameters are theta.
        posterior: the dynamics GP (``E = D`` outputs, inputs ``[a[model_inputs], u]``), detached.
        layout: the state layout shared with PILCO.
        cost: the planning cost: the task's cost with the planning width, or any cost with ``sample(x)``
            at states ``(..., D)`` (:class:`~plugins.mc_pilco.costs.StateCost`); only its values at the
            particles are used, never moments.
        init_mean, init_cov: ``(D,)``, ``(D, D)``.
        horizon: predicted and costed steps ``H``.
        particles: ``N``.
        cuda_graph: on a GPU, :meth:`value_and_grad` captures J_hat and its gradient as a CUDA graph
            (one per dropout value) and replays it for every Adam step; ``False``: every operation is
            launched anew each step. The random numbers are still drawn on the CPU and copied into the
            graph's input buffers, so the graph computes what the launched operations would.
    """

    controller: torch.nn.Module
    posterior: GPPosterior
    layout: StateLayout
    cost: CostMoments | StateCost
    init_mean: torch.Tensor
    init_cov: torch.Tensor
    horizon: int
    particles: int
    cuda_graph: bool = True
    #: why capturing failed, if it did (then every step launches its operations)
    graph_error: str | None = field(default=None, init=False, repr=False)
    _graphs: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.particles < 1:
            raise ValueError(f"particles must be >= 1, got {self.particles}")
        eigval, eigvec = torch.linalg.eigh(self.init_cov)  # a square root that also takes a singular Sigma0
        self._root = eigvec * eigval.clamp_min(0.0).sqrt()

    def draw(self, generator: torch.Generator, dropout: float = 0.0) -> ParticleDraws:
        """One rollout's random numbers from ``generator`` (a CPU generator), on the CPU."""
        d, n = self.init_mean.shape[0], self.particles
        init = torch.randn(n, d, generator=generator, dtype=torch.float64, device="cpu")
        shape = dropout_shape(self.controller, n, dropout)
        noise, keep = [], []
        for _ in range(self.horizon):
            if shape is not None:
                keep.append(torch.rand(shape, generator=generator, dtype=torch.float64, device="cpu") >= dropout)
            noise.append(torch.randn(n, d, generator=generator, dtype=torch.float64, device="cpu"))
        return ParticleDraws(init, torch.stack(noise) if noise else init.new_zeros(0, n, d),
                             torch.stack(keep) if keep else None)

    def rollout(self, generator: torch.Generator, dropout: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Sampled states ``(H+1, N, D)`` and the per-step mean cost ``(H,)`` of ``x_1..x_H``, both
        differentiable wrt the controller's parameters; ``generator`` (a CPU generator) draws the
        initial states, the model's noise and the dropout masks (:meth:`draw`). The objective computes
        where its tensors are (``init_mean``'s device: the posterior, controller and cost must be there
        too); the random numbers are drawn on the CPU and copied, so a GPU gets the same ones as the CPU."""
        return self.rollout_drawn(self.draw(generator, dropout).to(self.init_mean.device), dropout)

    def rollout_drawn(self, draws: ParticleDraws, dropout: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`rollout` with the random numbers given (on the objective's device)."""
        device = self.init_mean.device
        x = self.init_mean + draws.init @ self._root.T
        layout = self.layout
        policy_index, model_index = layout.on("policy_index", device), layout.on("model_index", device)
        base = self.controller.base if isinstance(self.controller, SquashedController) else self.controller
        post = base.posterior() if isinstance(base, RBFController) else None  # once per rollout
        states, costs = [x], []
        for t in range(self.horizon):
            a = layout.augment(x)
            keep = None if draws.keep is None else draws.keep[t]
            u = policy_actions(self.controller, a[:, policy_index], dropout, keep=keep, posterior=post)
            mean, var = predict_latent(self.posterior, torch.cat([a[:, model_index], u], dim=1))
            x = x + mean + var.clamp_min(VAR_FLOOR).sqrt() * draws.noise[t]
            states.append(x)
            costs.append(self.cost.sample(x).mean())
        return torch.stack(states), torch.stack(costs)

    def value(self, generator: torch.Generator, dropout: float = 0.0) -> torch.Tensor:
        """``J_hat`` (a differentiable scalar)."""
        return self.rollout(generator, dropout)[1].sum()

    def parameters(self) -> list[torch.Tensor]:
        """The controller's trainable parameters (theta), in ``controller.parameters()`` order."""
        return [p for p in self.controller.parameters() if p.requires_grad]

    def value_and_grad(self, generator: torch.Generator, dropout: float = 0.0) -> tuple[float, bool, list[torch.Tensor | None]]:
        """One Adam step's estimate: ``(J_hat, usable, dJ_hat/dtheta)`` for fresh random numbers from ``generator``.

        ``usable`` is False when J_hat or its gradient is not finite (the step is skipped); the gradient
        is one tensor per :meth:`parameters` entry (``None`` for one that J_hat does not depend on).
        On the CPU this is :meth:`value` and autograd. On a GPU (with ``cuda_graph``) the computation is
        captured once per dropout value and replayed; the host reads J_hat and two flags once per step,
        and a step whose factorisations failed is redone with the checks in place, so it raises as on
        the CPU.
        """
        params = self.parameters()
        draws = self.draw(generator, dropout)
        if self.cuda_graph and self.init_mean.device.type == "cuda" and self.graph_error is None:
            out = self._replay(draws, dropout, params)
            if out is not None:
                return out
        return self._launched(draws.to(self.init_mean.device), dropout, params)

    def _launched(self, draws: ParticleDraws, dropout: float, params: list[torch.Tensor]) -> tuple[float, bool, list]:
        J = self.rollout_drawn(draws, dropout)[1].sum()
        value = float(J.detach())
        if not math.isfinite(value):
            return value, False, [None] * len(params)
        grads = list(torch.autograd.grad(J, params, allow_unused=True))
        return value, all(bool(torch.isfinite(g).all()) for g in grads if g is not None), grads

    def _graph_output(self, draws: ParticleDraws, dropout: float, params: list[torch.Tensor]) -> torch.Tensor:
        """``[J_hat, failed, finite, dJ_hat...]`` on the device, the factorisations' checks deferred (no host read)."""
        with deferred_checks() as flags:
            J = self.rollout_drawn(draws, dropout)[1].sum()
            grads = torch.autograd.grad(J, params, allow_unused=True)
            failed = any_failed(flags, J)
        if any(g is None for g in grads):
            raise RuntimeError("a controller parameter does not enter J_hat (no gradient to capture)")
        flat = torch.cat([g.reshape(-1) for g in grads])
        finite = torch.isfinite(J) & torch.isfinite(flat).all()
        return torch.cat([J.detach().reshape(1), failed.to(J.dtype).reshape(1), finite.to(J.dtype).reshape(1), flat])

    def _replay(self, draws: ParticleDraws, dropout: float, params: list[torch.Tensor]):
        """:meth:`value_and_grad` through the CUDA graph for this dropout value (captured at its first
        use, after two launched warm-up runs on a side stream), or ``None`` if capturing failed
        (:attr:`graph_error` says why; the caller launches the operations)."""
        device = self.init_mean.device
        key = None if draws.keep is None else float(dropout)  # the dropout value enters the graph only with masks
        if key not in self._graphs:
            static = draws.to(device)
            try:
                graph, out = capture_cuda_graph(device, lambda: self._graph_output(static, dropout, params))
            except RuntimeError as exc:
                self.graph_error = capture_failure(exc)
                return None
            self._graphs[key] = (static, graph, out)
        static, graph, out = self._graphs[key]
        static.init.copy_(draws.init)
        static.noise.copy_(draws.noise)
        if static.keep is not None:
            static.keep.copy_(draws.keep)
        graph.replay()
        value, failed, finite = out[:3].tolist()  # the one host read of the step
        if failed:
            return self._launched(draws.to(device), dropout, params)  # with the checks: raises (or retries) as on the CPU
        if not finite:
            return value, False, [None] * len(params)
        grads, offset = [], 3
        for p in params:
            grads.append(out[offset:offset + p.numel()].reshape(p.shape).clone())
            offset += p.numel()
        return value, True, grads
