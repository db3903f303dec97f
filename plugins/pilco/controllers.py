"""Policies with exact output moments under Gaussian inputs (reference ``congp``, ``conlin``, ``gSat``).

Every controller maps policy inputs ``x (p,)`` to controls ``(F,)`` and offers

* ``forward(x)``: the deterministic control for a known input (``x (..., p)`` -> ``(..., F)``);
* ``moment_map(kernel=None)``: a :class:`MomentStage` (``kernel``: the contraction of any moment
  matching inside it, :func:`~plugins.pilco.moments.resolve_kernel`), callable as ``(m (p,), S (p, p)) -> (M (F,), V (F, F),
  C (p, F))`` with ``cov[x, u] = S @ C`` for ``x ~ N(m, S)``. Parameter-only work (e.g. the RBF
  weights) is done once when the map is built, so build it once per policy evaluation, not once
  per time step. A stage also offers the same moments as an explicit forward/backward pair
  (:meth:`MomentStage.forward`, :meth:`MomentStage.backward`), which the rollout chains into one
  autograd node for all time steps (:mod:`plugins.pilco.propagate`).

Controllers are ``torch.nn.Module``s whose ``parameters()`` are exactly the policy parameters theta.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from torch import nn

from plugins.pilco.kernels import cho_inverse, cho_solve, cholesky, se_ard
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.trig import SQUASH_KINDS, _sin_backward, _sin_forward, squash, squash_maps, squash_moments

MomentMap = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


@runtime_checkable
class MomentStage(Protocol):
    """A controller's moment map ``(m (p,), S (p, p)) -> (M (F,), V (F, F), C (p, F))``, twice:

    * ``stage(m, S)``: differentiable by autograd (the reference path);
    * ``stage.forward(m, S) -> ((M, V, C), saved)`` without a graph, and
      ``stage.backward(saved, gM, gV, gC, needs) -> (g_m, g_S, *g_tensors)``: the hand-derived
      gradients wrt ``m``, ``S`` and ``stage.tensors`` (the parameter-derived tensors the moments
      depend on; ``needs[i]`` says whether ``tensors[i]`` needs one, ``None`` is returned if not).
    """

    tensors: tuple[torch.Tensor, ...]

    def __call__(self, m: torch.Tensor, S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]: ...

    def forward(self, m: torch.Tensor, S: torch.Tensor) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], tuple]: ...

    def backward(self, saved: tuple, gM: torch.Tensor, gV: torch.Tensor, gC: torch.Tensor, needs) -> tuple: ...


class GPMeanStage:
    """Moments of a GP's *mean function* (``mean_only`` moment matching; the RBF policy)."""

    def __init__(self, gp: MomentMatchingGP) -> None:
        self.gp = gp
        self.tensors = gp.constants

    def __call__(self, m, S):
        return self.gp.predict(m, S, mean_only=True)

    def forward(self, m, S):
        return self.gp.forward(m, S, mean_only=True)

    def backward(self, saved, gM, gV, gC, needs):
        return self.gp.backward(saved, gM, gV, gC, True, (True, True, *needs))


class LinearStage:
    """``u = W x + b``: ``M = W m + b``, ``V = W S W^T``, ``C = W^T`` (exact). ``W (F, p)``, ``b (F,)``."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor) -> None:
        self.tensors = (weight, bias)

    def __call__(self, m, S):
        W, b = self.tensors
        return W @ m + b, W @ S @ W.T, W.T

    def forward(self, m, S):
        return self(m, S), (m, S)

    def backward(self, saved, gM, gV, gC, needs):
        (W, _), (m, S) = self.tensors, saved
        g_W = torch.outer(gM, m) + gV @ W @ S.T + gV.T @ W @ S + gC.T if needs[0] else None
        return W.T @ gM, W.T @ gV @ W, g_W, gM if needs[1] else None


class SquashStage:
    """A base stage followed by squashing ``u = G sin(A z)`` (:func:`~plugins.pilco.trig.squash_maps`).

    Moments of ``u``: ``M = G E[sin]``, ``V = G cov[sin] G^T``, ``C = C_base C_sin G^T``.
    """

    def __init__(self, base: MomentStage, u_max: torch.Tensor, kind: str) -> None:
        self.base, self.u_max, self.kind = base, u_max, kind
        self.maps = squash_maps(u_max, kind)
        self.tensors = base.tensors

    def __call__(self, m, S):
        mz, sz, cz = self.base(m, S)
        mu, su, cu = squash_moments(mz, sz, self.u_max, self.kind, self.maps)
        return mu, su, cz @ cu

    def forward(self, m, S):
        A, G = self.maps
        (mz, sz, cz), saved_base = self.base.forward(m, S)
        (ms, vs, cs), saved_sin = _sin_forward(mz, sz, A, None)
        cu = cs @ G.T  # (F, F)
        return (ms @ G.T, G @ vs @ G.T, cz @ cu), (saved_base, saved_sin, cz, cu)

    def backward(self, saved, gM, gV, gC, needs):
        A, G = self.maps
        saved_base, saved_sin, cz, cu = saved
        g_mz, g_sz = _sin_backward(A, saved_sin, gM @ G, G.T @ gV @ G, (cz.T @ gC) @ G)
        return self.base.backward(saved_base, g_mz, g_sz, gC @ cu.T, needs)

#: fixed RBF-policy signal standard deviation and noise standard deviation (reference congp)
RBF_SIGNAL_STD = 1.0
RBF_NOISE_STD = 0.01


class RBFController(nn.Module):
    """RBF network = mean of a GP on pseudo-data (reference ``congp``), one GP per control.

    ``z_a(x) = sum_i beta_ai exp(-1/2 (x - c_i)^T Lambda_a^-1 (x - c_i))`` with
    ``beta_a = (K_a + 0.01^2 I)^-1 t_a``, ``K_a`` the SE-ARD Gram matrix of the centres with signal
    variance fixed to 1. Output moments are the GP-mean moments (``mean_only``, reference ``gp2``;
    gp2's extra 1e-6 on the output variance is not added: the moments here are exact).

    Parameters (theta): ``centres (n_c, p)``, ``targets (n_c, F)``, ``log_ell (F, p)``;
    count ``n_c p + n_c F + F p`` (305 for 50 centres, 5 inputs, 1 control: the paper's R^305).
    """

    def __init__(self, centres: torch.Tensor, targets: torch.Tensor, log_ell: torch.Tensor) -> None:
        super().__init__()
        if centres.ndim != 2 or targets.ndim != 2 or targets.shape[0] != centres.shape[0]:
            raise ValueError("centres must be (n_c, p) and targets (n_c, F)")
        if log_ell.shape != (targets.shape[1], centres.shape[1]):
            raise ValueError(f"log_ell must have shape (F, p) = {(targets.shape[1], centres.shape[1])}")
        self.centres = nn.Parameter(centres.detach().clone().to(torch.float64))
        self.targets = nn.Parameter(targets.detach().clone().to(torch.float64))
        self.log_ell = nn.Parameter(log_ell.detach().clone().to(torch.float64))

    @classmethod
    def initial(
        cls,
        input_mean: torch.Tensor,
        input_cov: torch.Tensor,
        num_centres: int,
        num_controls: int,
        length_scales: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> RBFController:
        """Reference initialisation: centres ~ N(input_mean, input_cov), targets = 0.1 randn,
        length-scales ``(p,)`` (shared by all controls) or ``(F, p)``."""
        p = input_mean.shape[0]
        chol = torch.linalg.cholesky(input_cov.to(torch.float64) + 1e-12 * torch.eye(p, dtype=torch.float64))
        eps = torch.randn(num_centres, p, generator=generator, dtype=torch.float64)
        return cls.at_centres(input_mean.to(torch.float64) + eps @ chol.T, num_controls, length_scales, generator)

    @classmethod
    def at_centres(cls, centres: torch.Tensor, num_controls: int, length_scales: torch.Tensor,
                   generator: torch.Generator | None = None, target_scale: float | None = None) -> RBFController:
        """The reference's targets (0.1 randn, drawn with ``generator``) and length-scales (``(p,)`` shared by
        all controls, or ``(F, p)``) at given ``centres (n_c, p)``. With ``target_scale`` the targets are
        uniform in ``[-target_scale, target_scale]`` instead (MC-PILCO's random initial weights)."""
        shape = (centres.shape[0], num_controls)
        if target_scale is None:
            targets = 0.1 * torch.randn(*shape, generator=generator, dtype=torch.float64)
        else:
            targets = float(target_scale) * (2.0 * torch.rand(*shape, generator=generator, dtype=torch.float64) - 1.0)
        log_ell = torch.log(torch.as_tensor(length_scales, dtype=torch.float64)).expand(num_controls, centres.shape[1])
        return cls(centres, targets, log_ell)

    @property
    def num_controls(self) -> int:
        return int(self.targets.shape[1])

    def posterior(self) -> GPPosterior:
        """The pseudo-data GP as a :class:`GPPosterior` (inputs = centres)."""
        f = self.num_controls
        log_alpha = self.centres.new_full((f,), math.log(RBF_SIGNAL_STD))
        log_sigma = self.centres.new_full((f,), math.log(RBF_NOISE_STD))
        gram = se_ard(self.centres, self.centres, self.log_ell, log_alpha)  # (F, n_c, n_c)
        gram = gram + RBF_NOISE_STD**2 * torch.eye(self.centres.shape[0], dtype=torch.float64, device=self.centres.device)
        chol = cholesky(gram, "RBF policy Gram matrix")
        beta = cho_solve(chol, self.targets.T[..., None]).squeeze(-1)  # (F, n_c)
        return GPPosterior(self.centres, beta, cho_inverse(chol), self.log_ell, log_alpha, log_sigma)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        post = self.posterior()
        k = se_ard(x.reshape(-1, x.shape[-1]), post.inputs, post.log_ell, post.log_alpha)  # (F, N, n_c)
        z = torch.einsum("anm,am->na", k, post.beta)
        return z.reshape(*x.shape[:-1], self.num_controls)

    def moment_map(self, kernel: str | None = None) -> MomentStage:
        """``kernel`` ``None``: the torch contraction. The policy's GP is one output pair on
        ``n_c`` centres, ~1 % of a rollout's contraction work, and its Gram matrix (centres close
        together, noise 0.01) amplifies round-off: the compiled kernel's different summation order
        moved dJ by ~5e-7 relative on the double pendulum (torch's own change for a 1-ulp step of
        theta: ~2e-6), the dynamics GP's by ~5e-8."""
        return GPMeanStage(MomentMatchingGP(self.posterior(), kernel=kernel or "torch"))


class LinearController(nn.Module):
    """Linear policy ``u = W x + b`` (reference ``conlin``): M = W m + b, V = W S W^T, C = W^T.

    Parameters (theta): ``weight (F, p)``, ``bias (F,)``.
    """

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor) -> None:
        super().__init__()
        if weight.ndim != 2 or bias.shape != (weight.shape[0],):
            raise ValueError("weight must be (F, p) and bias (F,)")
        self.weight = nn.Parameter(weight.detach().clone().to(torch.float64))
        self.bias = nn.Parameter(bias.detach().clone().to(torch.float64))

    @classmethod
    def initial(cls, num_inputs: int, num_controls: int, scale: float = 0.1, generator: torch.Generator | None = None) -> LinearController:
        """Random weights ``scale * randn``, zero bias."""
        weight = scale * torch.randn(num_controls, num_inputs, generator=generator, dtype=torch.float64)
        return cls(weight, torch.zeros(num_controls, dtype=torch.float64))

    @property
    def num_controls(self) -> int:
        return int(self.weight.shape[0])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight.T + self.bias

    def moment_map(self, kernel: str | None = None) -> MomentStage:
        return LinearStage(self.weight, self.bias)


class SquashedController(nn.Module):
    """A controller followed by squashing to ``[-u_max, u_max]`` (reference ``conCat`` + ``gSat``).

    ``kind``: ``"trapezoid"`` (``u_max (9 sin z + sin 3z)/8``), ``"sin"`` (``u_max sin z``) or
    ``None`` (no squashing). Cross-covariances chain: ``C = C_base @ C_squash``.
    """

    def __init__(self, base: nn.Module, u_max, kind: str | None = "trapezoid") -> None:
        super().__init__()
        if kind is not None and kind not in SQUASH_KINDS:
            raise ValueError(f"unknown squashing {kind!r}; expected one of {SQUASH_KINDS} or None")
        self.base = base
        self.kind = kind
        self.register_buffer("u_max", torch.as_tensor(u_max, dtype=torch.float64).reshape(-1).clone())
        if self.u_max.shape[0] != base.num_controls:
            raise ValueError(f"u_max has {self.u_max.shape[0]} entries for {base.num_controls} controls")

    @property
    def num_controls(self) -> int:
        return self.base.num_controls

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.base(x)
        return z if self.kind is None else squash(z, self.u_max, self.kind)

    def moment_map(self, kernel: str | None = None) -> MomentStage:
        base_stage = self.base.moment_map(kernel)
        return base_stage if self.kind is None else SquashStage(base_stage, self.u_max, self.kind)


#: the controllers a saved policy may hold, by the name it is saved under, with their parameters in constructor order
CONTROLLER_TYPES: dict[str, tuple[type[nn.Module], tuple[str, ...]]] = {
    "rbf": (RBFController, ("centres", "targets", "log_ell")),
    "linear": (LinearController, ("weight", "bias")),
}


def controller_state(controller: SquashedController) -> dict[str, Any]:
    """A squashed controller as plain data: ``type`` (a :data:`CONTROLLER_TYPES` name), ``squash`` (its
    kind or ``None``), ``u_max (F,)`` and ``parameters`` (the base controller's tensors by name)."""
    names = {cls: name for name, (cls, _) in CONTROLLER_TYPES.items()}
    if not isinstance(controller, SquashedController) or type(controller.base) not in names:
        raise TypeError(f"a PILCO policy's controller is a SquashedController of {sorted(CONTROLLER_TYPES)}, not {controller!r}")
    return {"type": names[type(controller.base)], "squash": controller.kind, "u_max": controller.u_max.detach().clone(),
            "parameters": {name: p.detach().clone() for name, p in controller.base.named_parameters()}}


def controller_from_state(state: dict[str, Any]) -> SquashedController:
    """The controller :func:`controller_state` described (``KeyError``/``TypeError``/``ValueError`` if it describes none)."""
    cls, names = CONTROLLER_TYPES[state["type"]]
    parameters = state["parameters"]
    if not isinstance(parameters, dict) or set(parameters) != set(names):
        raise ValueError(f"a {state['type']} controller has parameters {list(names)}, not {sorted(parameters)}")
    if not all(isinstance(parameters[n], torch.Tensor) for n in names) or not isinstance(state["u_max"], torch.Tensor):
        raise TypeError("controller parameters and u_max must be tensors")
    return SquashedController(cls(*(parameters[n] for n in names)), state["u_max"], state["squash"])
