"""State-distribution propagation through the policy and the GP dynamics (reference ``propagate.m``).

One step maps ``p(x_t) = N(m, S)`` (``x (D,)``) to a Gaussian ``p(x_{t+1})``:

1. augment: ``a = [x, sin(x_angles), cos(x_angles)]`` (``D + 2K``), moments by :mod:`trig`;
2. policy: ``u = pi(a[policy_inputs])``; its mean, covariance and ``cov[a, u] = S_a[:, pol] C_u``;
3. dynamics: ``Delta = f([a[model_inputs], u])`` by moment matching (:mod:`moments`) with
   ``cov[x, Delta] = cov[x, inputs] C_Delta``;
4. ``m' = m + M_Delta``, ``S' = S + V_Delta + cov[x, Delta] + cov[x, Delta]^T`` (symmetrised).

Every dimension of ``x`` is predicted as a difference (the GP has ``E = D`` outputs). The
cross-covariances chain in the package convention ``cov[x, g(x)] = S @ C`` (see :mod:`moments`),
which is exact for the jointly Gaussian approximations made at each stage (paper eq. 12).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from plugins.pilco.controllers import MomentMap
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.trig import augment_trig


@dataclass(frozen=True)
class StateLayout:
    """How a state ``x (D,)`` is presented to the dynamics model and to the policy.

    The augmented state is ``a = [x (D), sin(x[angle_indices]) (K), cos(x[angle_indices]) (K)]``;
    ``model_inputs`` and ``policy_inputs`` index into ``a``. The GP input is
    ``[a[model_inputs], u]``. Cart-pole (``x = [x, xdot, thetadot, theta]``, angle 3):
    ``a = [x, xdot, thetadot, theta, sin theta, cos theta]``, inputs ``(0, 1, 2, 4, 5)``
    (what :meth:`with_trig` builds).
    """

    state_dim: int
    angle_indices: tuple[int, ...]
    model_inputs: tuple[int, ...]
    policy_inputs: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "angle_indices", tuple(int(i) for i in self.angle_indices))
        object.__setattr__(self, "model_inputs", tuple(int(i) for i in self.model_inputs))
        object.__setattr__(self, "policy_inputs", tuple(int(i) for i in self.policy_inputs))
        if any(not 0 <= i < self.state_dim for i in self.angle_indices):
            raise ValueError(f"angle_indices {self.angle_indices} out of range for D = {self.state_dim}")
        for name in ("model_inputs", "policy_inputs"):
            idx = getattr(self, name)
            if not idx or any(not 0 <= i < self.augmented_dim for i in idx) or len(set(idx)) != len(idx):
                raise ValueError(f"{name} {idx} must be distinct indices into the {self.augmented_dim} augmented entries")

    @classmethod
    def with_trig(cls, state_dim: int, angle_indices) -> StateLayout:
        """Model and policy both see the non-angle entries and sin/cos of every angle (not the raw angle)."""
        angles = tuple(int(i) for i in angle_indices)
        k = len(angles)
        inputs = tuple(i for i in range(state_dim) if i not in angles) + tuple(range(state_dim, state_dim + 2 * k))
        return cls(state_dim, angles, inputs, inputs)

    @property
    def num_angles(self) -> int:
        return len(self.angle_indices)

    @property
    def augmented_dim(self) -> int:
        return self.state_dim + 2 * self.num_angles

    @property
    def model_input_dim(self) -> int:
        """GP input dimension excluding the controls."""
        return len(self.model_inputs)

    @cached_property
    def angle_map(self) -> torch.Tensor:
        """``(K, D)`` selector of the angle entries."""
        A = torch.zeros(self.num_angles, self.state_dim, dtype=torch.float64)
        A[torch.arange(self.num_angles), torch.tensor(self.angle_indices, dtype=torch.long)] = 1.0
        return A

    @cached_property
    def policy_index(self) -> torch.Tensor:
        return torch.tensor(self.policy_inputs, dtype=torch.long)

    @cached_property
    def model_index(self) -> torch.Tensor:
        return torch.tensor(self.model_inputs, dtype=torch.long)

    def augment(self, x: torch.Tensor) -> torch.Tensor:
        """Deterministic ``a(x)`` for ``x (..., D)``."""
        phi = x @ self.angle_map.T
        return torch.cat([x, torch.sin(phi), torch.cos(phi)], dim=-1)


def propagate_step(
    m: torch.Tensor,
    S: torch.Tensor,
    dynamics: MomentMatchingGP,
    policy_moments: MomentMap,
    layout: StateLayout,
    mean_only: bool = False,
    slot: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``N(m, S)`` at time t -> ``(m', S')`` at t+1. ``m (D,)``, ``S (D, D)``.

    ``dynamics`` is ``MomentMatchingGP(posterior)``, ``policy_moments`` is
    ``controller.moment_map()`` (build both once per rollout); ``mean_only`` is passed to
    :meth:`~plugins.pilco.moments.MomentMatchingGP.predict` (deterministic-GP-mean ablation),
    ``slot`` too (work-buffer reuse across rollouts; the rollout passes the time step).
    """
    d = layout.state_dim
    ma, sa = augment_trig(m, S, layout.angle_map)  # (A,), (A, A)
    pol, mod = layout.policy_index, layout.model_index

    mu, su, cu = policy_moments(ma[pol], sa[pol[:, None], pol[None, :]])
    s_au = sa[:, pol] @ cu  # (A, F) cov[a, u]

    s_a_mod = sa[:, mod]  # (A, q) cov[a, a_mod]
    s_mod_u = s_au[mod]  # (q, F)
    m_in = torch.cat([ma[mod], mu])
    s_in = torch.cat(
        [torch.cat([s_a_mod[mod], s_mod_u], dim=1), torch.cat([s_mod_u.T, su], dim=1)], dim=0
    )
    md, vd, cd = dynamics.predict(m_in, s_in, mean_only=mean_only, slot=slot)
    s_x_in = torch.cat([s_a_mod[:d], s_au[:d]], dim=1)  # (D, q + F) cov[x, GP input]
    s_xd = s_x_in @ cd  # (D, D) cov[x, Delta]
    s_next = S + vd + s_xd + s_xd.T
    return m + md, 0.5 * (s_next + s_next.T)


def rollout(
    m0: torch.Tensor,
    S0: torch.Tensor,
    horizon: int,
    posterior: GPPosterior | MomentMatchingGP,
    controller: torch.nn.Module,
    layout: StateLayout,
    mean_only: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted state distributions over ``horizon`` steps from ``N(m0, S0)``.

    ``posterior``: the dynamics GP, or a :class:`MomentMatchingGP` of it kept across rollouts (as
    :class:`~plugins.pilco.objective.PolicyObjective` does) to reuse its work buffers.
    Returns means ``(H+1, D)`` and covariances ``(H+1, D, D)``; index 0 is the initial state.
    """
    dynamics = posterior if isinstance(posterior, MomentMatchingGP) else MomentMatchingGP(posterior)
    posterior = dynamics.posterior
    if posterior.num_outputs != layout.state_dim:
        raise ValueError(f"the dynamics GP has {posterior.num_outputs} outputs; the state has {layout.state_dim}")
    expected = layout.model_input_dim + controller.num_controls
    if posterior.input_dim != expected:
        raise ValueError(f"the dynamics GP takes {posterior.input_dim} inputs; layout + controls give {expected}")
    policy_moments = controller.moment_map()
    means, covs = [m0], [S0]
    m, S = m0, S0
    for t in range(horizon):
        m, S = propagate_step(m, S, dynamics, policy_moments, layout, mean_only, slot=t)
        means.append(m)
        covs.append(S)
    return torch.stack(means), torch.stack(covs)


def act(x, controller: torch.nn.Module, layout: StateLayout) -> np.ndarray:
    """The policy applied to an observed state ``x (D,)``: augment, controller, squash -> ``u (F,)``."""
    xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
    with torch.no_grad():
        u = controller(layout.augment(xt)[layout.policy_index])
    return u.numpy().copy()
