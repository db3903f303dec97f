"""Expected saturating cost under a Gaussian state (reference ``lossSat``), in residual space.

The task's cost (:class:`harness.task.SaturatingCost`) is, with the **1/2-width convention**::

    c(x) = 1 - exp(-|r|^2 / (2 width^2)),   r = C a(x) - target,   a(x) = [x, sin(A x), cos(A x)].

For ``x ~ N(m, S)``, ``a(x)`` is moment-matched by a Gaussian ``N(m_a, S_a)`` (exact first and second
moments, :func:`~plugins.pilco.trig.augment_trig`; the reference's gTrig step), so the residual is
Gaussian ``r ~ N(m_r, S_r)``, ``m_r = C m_a - target``, ``S_r = C S_a C^T`` (``P`` entries), and for
``w = width``::

    E[exp(-|r|^2 / (2 w^2))] = |I + S_r / w^2|^-1/2  exp(-1/2 m_r^T (S_r + w^2 I)^-1 m_r)
    E[exp(-|r|^2 / w^2)]     = |I + 2 S_r / w^2|^-1/2 exp(-1/2 m_r^T (S_r + w^2/2 I)^-1 m_r)
    E[c] = 1 - first,   Var[c] = second - first^2.

This equals lossSat with ``W = C^T C / w^2`` in the ``a``-space (``r`` is an affine image of ``a``),
but works with the ``P x P`` residual covariance (``P = 2`` for the cart-pole tip) and never needs a
``z`` with ``C z = target``. With no angles (``K = 0``) the result is exact for Gaussian ``x``.
"""

from __future__ import annotations

import math

import torch

from harness.errors import NumericalError
from harness.task import SaturatingCost
from plugins.pilco.kernels import deferred_flags
from plugins.pilco.trig import augment_trig


def gaussian_saturation(m_r: torch.Tensor, S_r: torch.Tensor, width: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``E`` and ``Var`` of ``1 - exp(-|r|^2/(2 width^2))`` for ``r ~ N(m_r, S_r)``.

    Args: ``m_r (..., P)``, ``S_r (..., P, P)``. Returns two tensors of shape ``(...)``.
    """
    p = m_r.shape[-1]
    eye = torch.eye(p, dtype=S_r.dtype, device=S_r.device)

    def expected_gauss(scale2: float) -> torch.Tensor:
        # E[exp(-|r|^2 / (2 scale2))] = |I + S_r/scale2|^-1/2 exp(-1/2 m^T (S_r + scale2 I)^-1 m)
        chol, info = torch.linalg.cholesky_ex(S_r + scale2 * eye)
        flags = deferred_flags()
        if flags is not None:
            flags.append(info)
        elif bool((info != 0).any()):
            bad = torch.nonzero(info.reshape(-1)).reshape(-1).tolist()
            raise NumericalError(
                f"the predicted cost's covariance is not positive definite at prediction step(s) {bad[:5]} "
                "(the propagated state distribution degenerated; the policy search treats this point as +inf)"
            )
        half_logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1) - 0.5 * p * math.log(scale2)
        y = torch.linalg.solve_triangular(chol, m_r[..., None], upper=False).squeeze(-1)
        return torch.exp(-half_logdet - 0.5 * (y * y).sum(-1))

    w2 = float(width) ** 2
    first = expected_gauss(w2)
    second = expected_gauss(0.5 * w2)
    return 1.0 - first, (second - first * first).clamp_min(0.0)


class CostMoments:
    """The task's :class:`SaturatingCost` as torch tensors, with its moments under Gaussian states."""

    def __init__(self, cost: SaturatingCost, width: float | None = None, device: torch.device | str | None = None) -> None:
        self.cost = cost
        self.width = float(cost.width if width is None else width)
        self.angle_map = torch.as_tensor(cost.angle_map, dtype=torch.float64, device=device)
        self.linear_map = torch.as_tensor(cost.linear_map, dtype=torch.float64, device=device)
        self.target = torch.as_tensor(cost.target, dtype=torch.float64, device=device)

    def sample(self, x: torch.Tensor) -> torch.Tensor:
        """The cost at known states ``x (..., D)`` -> ``(...)``, with this object's width."""
        phi = x @ self.angle_map.T
        r = torch.cat([x, torch.sin(phi), torch.cos(phi)], dim=-1) @ self.linear_map.T - self.target
        return 1.0 - torch.exp(-(r * r).sum(-1) / (2.0 * self.width**2))

    def residual_moments(self, m: torch.Tensor, S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussian ``r = C a(x) - target`` for ``x ~ N(m, S)``: ``(..., P)``, ``(..., P, P)``."""
        ma, sa = augment_trig(m, S, self.angle_map)
        C = self.linear_map
        return ma @ C.T - self.target, C @ sa @ C.T

    def __call__(self, m: torch.Tensor, S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``E[c(x)]`` and ``Var[c(x)]`` for ``x ~ N(m, S)``, ``m (..., D)``, ``S (..., D, D)`` -> ``(...)``."""
        m_r, s_r = self.residual_moments(m, S)
        return gaussian_saturation(m_r, s_r, self.width)
