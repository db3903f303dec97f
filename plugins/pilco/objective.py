"""The policy objective J(theta) = sum_{t=1..H} E[c(x_t)] and its gradient (reference ``value.m``).

``x_0 ~ N(mu0, Sigma0)`` is not costed (gamma = 1, as in all reference scenarios). J is a closed-form
function of theta (moment matching all the way), so its gradient is exact: ``torch.autograd`` runs
the chain rule of paper eqs. 26-30, through one hand-differentiated node for the whole rollout
(:class:`~plugins.pilco.propagate.FusedStep`) and ordinary autograd for the policy's parameters
-> RBF network and for the cost.

:class:`PolicyObjective` also adapts J to ``scipy.optimize.minimize(..., jac=True)``: it packs the
controller parameters into one flat float64 vector (in ``controller.parameters()`` order) and
evaluates ``vector -> (J, dJ/dtheta)`` with the dynamics posterior detached.
"""

from __future__ import annotations

import numpy as np
import torch

from harness.task import SaturatingCost
from plugins.pilco.cost import CostMoments
from plugins.pilco.kernels import any_failed, capture_cuda_graph, capture_failure, deferred_checks
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.propagate import StateLayout, rollout


class PolicyObjective:
    """J(theta) for one dynamics model, controller, cost and initial distribution.

    Args:
        controller: a controller module (e.g. ``SquashedController``); its parameters are theta.
        posterior: the dynamics GP (``E = D`` outputs, inputs ``[a[model_inputs], u]``); detached.
        layout: the :class:`StateLayout`.
        cost: the task's saturating cost (``width`` overrides its width if given).
        init_mean, init_cov: ``(D,)``, ``(D, D)``.
        horizon: number of predicted (and costed) steps H.
        mean_only: deterministic-GP-mean ablation (see :func:`~plugins.pilco.moments.predict_uncertain`).
        width: planning cost width (``None``: the cost's own).
        policy_noise_std: ``(D,)`` std of the measurement noise the policy will act through, or
            ``None`` (the policy sees the latent state, as in the reference code's last version);
            see :meth:`~plugins.pilco.propagate.StateLayout.policy_noise_cov`.
        kernel: the dynamics GP's contraction (:func:`~plugins.pilco.moments.resolve_kernel`:
            ``None``/``"auto"``, ``"fused"``, ``"numba"``, ``"torch"``); ``threads``: threads it may use.
        device: where J is computed (``None``: where the posterior is, normally the CPU; e.g.
            ``"cuda"``). The posterior, the distributions and the controller are moved there (the
            controller in place); theta goes in and dJ comes out as NumPy arrays on the host.
        cuda_graph: on a GPU, capture J + dJ once as a CUDA graph and replay it for every theta
            (:meth:`value_and_grad`); ``False``: launch every operation anew each time.
        compile_step: run each rollout step as code made by ``torch.compile``
            (:class:`~plugins.pilco.propagate.FusedStep`: the elementwise operations fused into fewer
            kernels, for a GPU, where their launches set the time; made at the first evaluation).
            Needs the ``torch`` kernel (the default off the CPU).

    Off the CPU, J + dJ runs with its factorisations' failure checks deferred to the end
    (:func:`~plugins.pilco.kernels.deferred_checks`: one host read per evaluation instead of one
    per step); if one failed, the evaluation is redone with the checks in place, so it raises (or
    retries with jitter) exactly as on the CPU.
    """

    def __init__(
        self,
        controller: torch.nn.Module,
        posterior: GPPosterior,
        layout: StateLayout,
        cost: SaturatingCost,
        init_mean,
        init_cov,
        horizon: int,
        mean_only: bool = False,
        width: float | None = None,
        policy_noise_std=None,
        kernel: str | None = None,
        threads: int = 1,
        device: torch.device | str | None = None,
        cuda_graph: bool = True,
        compile_step: bool = False,
    ) -> None:
        self.device = posterior.beta.device if device is None else torch.device(device)
        self.controller = controller.to(self.device)
        self.posterior = posterior.detach().to(self.device)
        # kept: precomputed constants, work buffers
        self.dynamics = MomentMatchingGP(self.posterior, kernel=kernel, threads=threads)
        self.compile_step = bool(compile_step)
        if self.compile_step and self.dynamics.kernel != "torch":
            raise ValueError(f"compile_step needs the torch kernel, not {self.dynamics.kernel!r}: "
                             "pass kernel='torch' (the default off the CPU) or leave compile_step off")
        self.layout = layout
        self.cost = CostMoments(cost, width, self.device)
        self.init_mean = torch.as_tensor(np.asarray(init_mean, dtype=np.float64), device=self.device)
        self.init_cov = torch.as_tensor(np.asarray(init_cov, dtype=np.float64), device=self.device)
        self.horizon = int(horizon)
        self.mean_only = bool(mean_only)
        self.policy_noise = None if policy_noise_std is None else layout.policy_noise_cov(policy_noise_std).to(self.device)
        self.params = [p for p in controller.parameters() if p.requires_grad]
        self.num_params = sum(p.numel() for p in self.params)
        self.policy_noise_std = policy_noise_std
        self.defer_checks = self.device.type != "cpu"  # see the class docstring
        self.cuda_graph = bool(cuda_graph) and self.device.type == "cuda"
        self.graph_error: str | None = None  # why capturing failed, if it did (then every evaluation runs eagerly)
        self._graph = None  # (key, CUDAGraph, static output [J, failed, dJ...])

    # ---- closed form ----------------------------------------------------------------------------
    def state_distributions(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted ``means (H+1, D)``, ``covs (H+1, D, D)`` (index 0 = initial)."""
        return rollout(self.init_mean, self.init_cov, self.horizon, self.dynamics, self.controller, self.layout,
                       self.mean_only, self.policy_noise, self.compile_step)

    def step_costs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Expected cost and its variance for ``x_1 .. x_H``: two ``(H,)`` tensors."""
        means, covs = self.state_distributions()
        return self.cost(means[1:], covs[1:])

    def value(self) -> torch.Tensor:
        """J(theta) as a differentiable scalar tensor."""
        return self.step_costs()[0].sum()

    def predicted_costs(self) -> tuple[np.ndarray, np.ndarray]:
        """Predicted per-step cost mean and standard deviation for t = 1..H (numpy ``(H,)`` each)."""
        with torch.no_grad():
            mean, var = self.step_costs()
        return mean.cpu().numpy().copy(), var.sqrt().cpu().numpy().copy()

    # ---- flat-vector interface for scipy ---------------------------------------------------------
    def get_flat(self) -> np.ndarray:
        """theta as a flat float64 vector (``controller.parameters()`` order)."""
        return torch.cat([p.detach().reshape(-1) for p in self.params]).cpu().numpy().copy()

    def set_flat(self, theta: np.ndarray) -> None:
        """Write a flat vector back into the controller parameters."""
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape[0] != self.num_params:
            raise ValueError(f"theta has {theta.shape[0]} entries; the controller has {self.num_params} parameters")
        offset = 0
        with torch.no_grad():
            for p in self.params:
                n = p.numel()
                p.copy_(torch.from_numpy(theta[offset : offset + n]).reshape(p.shape))  # to the parameter's device
                offset += n

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """``(J, dJ/dtheta)`` at ``theta`` (the controller keeps ``theta`` afterwards)."""
        self.set_flat(theta)
        if self.defer_checks:
            out = self._graph_replay() if self.cuda_graph and self.graph_error is None else self._deferred_output()
            out = out.cpu().numpy()  # the one host read of the evaluation
            if not out[1]:
                return float(out[0]), out[2:].copy()
        return self._checked_value_and_grad()

    def _checked_value_and_grad(self) -> tuple[float, np.ndarray]:
        """J + dJ with every factorisation checked where it happens (raises as documented)."""
        J = self.value()
        grads = torch.autograd.grad(J, self.params)
        return float(J.detach()), torch.cat([g.reshape(-1) for g in grads]).cpu().numpy().copy()

    def _deferred_output(self) -> torch.Tensor:
        """``[J, failed, dJ...]`` as one tensor on the device, the factorisations' checks deferred
        (nothing read on the host: the computation can be captured in a CUDA graph)."""
        with deferred_checks() as flags:
            J = self.value()
            grads = torch.autograd.grad(J, self.params)
            failed = any_failed(flags, J)
        return torch.cat([J.detach().reshape(1), failed.to(J.dtype).reshape(1), *(g.reshape(-1) for g in grads)])

    def _graph_replay(self) -> torch.Tensor:
        """:meth:`_deferred_output` through a CUDA graph captured at the first call (after two
        eager warm-up calls on a side stream, as CUDA graphs require) and replayed after; the
        controller's parameters are the graph's input (written in place by :meth:`set_flat`).
        If capturing fails, :attr:`graph_error` says why and evaluations run eagerly from then on."""
        key = (self.horizon, self.mean_only, self.policy_noise is None)
        if self._graph is None or self._graph[0] != key:
            self._graph = None
            try:
                graph, static = capture_cuda_graph(self.device, self._deferred_output)
            except RuntimeError as exc:
                self.graph_error = capture_failure(exc)
                return self._deferred_output()
            self._graph = (key, graph, static)
        _, graph, static = self._graph
        graph.replay()
        return static

    __call__ = value_and_grad
