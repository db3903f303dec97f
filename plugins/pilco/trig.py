"""Exact moments of sines of Gaussian variables (reference ``gSin``/``gTrig``), and squashing.

Everything is one formula: for ``x ~ N(m, S)`` (``m (..., D)``, ``S (..., D, D)``) and an affine map
``y = A x + b`` (``A (K, D)``, ``b (K,)``), with ``mu = A m + b``, ``Vy = A S A^T``,
``e_i = exp(-Vy_ii / 2)``::

    E[sin y_i]              = e_i sin mu_i
    cov[sin y_i, sin y_j]   = e_i e_j / 2 [expm1(Vy_ij) cos(mu_i - mu_j) - expm1(-Vy_ij) cos(mu_i + mu_j)]
    S^-1 cov[x, sin y_i]    = A_i^T e_i cos mu_i          (Stein's lemma; column i of C (D, K))

``cos y = sin(y + pi/2)``, so ``[sin(A x), cos(A x)]`` is the case ``[A; A] x + [0; pi/2]``
(:func:`trig_moments`, the reference's gTrig for a linear map). Cross-covariances follow the
package convention ``cov[x, g(x)] = S @ C`` (see :mod:`plugins.pilco.moments`). All functions
broadcast over leading batch dimensions of ``m`` and ``S``.

Squashing of a control ``z`` to ``[-u_max, u_max]`` (reference ``gSat``)::

    "trapezoid":  u = u_max (9 sin z + sin 3z) / 8     (third-order Fourier series of a trapezoid)
    "sin":        u = u_max sin z

with exact moments via the augmented Gaussian ``[z; 3z]``.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

SQUASH_KINDS = ("trapezoid", "sin")


def sin_moments(
    m: torch.Tensor, S: torch.Tensor, A: torch.Tensor, b: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``sin(A x + b)`` for ``x ~ N(m, S)``.

    Args:
        m: ``(..., D)``; S: ``(..., D, D)``; A: ``(K, D)``; b: ``(K,)`` or ``None`` (zero).

    Returns:
        mean ``(..., K)``, covariance ``(..., K, K)``, ``C (..., D, K)`` with ``cov[x, sin y] = S @ C``.
    """
    mu = m @ A.T
    if b is not None:
        mu = mu + b
    vy = A @ S @ A.T  # (..., K, K)
    e = torch.exp(-0.5 * torch.diagonal(vy, dim1=-2, dim2=-1))  # (..., K)
    mean = e * torch.sin(mu)
    mu_i, mu_j = mu[..., :, None], mu[..., None, :]
    cov = (0.5 * e[..., :, None] * e[..., None, :]) * (
        torch.expm1(vy) * torch.cos(mu_i - mu_j) - torch.expm1(-vy) * torch.cos(mu_i + mu_j)
    )
    cross = A.T * (e * torch.cos(mu))[..., None, :]  # (..., D, K)
    return mean, cov, cross


@lru_cache(maxsize=64)
def _doubled(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``([A; A], [0; pi/2])`` for :func:`trig_moments` (cached per map tensor)."""
    k = A.shape[0]
    offset = torch.cat([torch.zeros(k, dtype=A.dtype), torch.full((k,), 0.5 * math.pi, dtype=A.dtype)])
    return torch.cat([A, A], dim=0), offset


def trig_moments(m: torch.Tensor, S: torch.Tensor, A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``[sin(A x), cos(A x)]`` (``2K`` entries) for ``x ~ N(m, S)``, ``A (K, D)``.

    Returns mean ``(..., 2K)``, covariance ``(..., 2K, 2K)``, ``C (..., D, 2K)`` (``cov[x, .] = S @ C``).
    """
    A2, offset = _doubled(A)
    return sin_moments(m, S, A2, offset)


def augment_trig(m: torch.Tensor, S: torch.Tensor, A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian approximation of ``a(x) = [x, sin(A x), cos(A x)]`` (``D + 2K`` entries).

    Returns mean ``(..., D + 2K)`` and covariance ``(..., D + 2K, D + 2K)``: exact first and second
    moments, the ``x`` block is ``S`` and the ``(x, trig)`` block is ``S @ C`` (:func:`trig_moments`).
    """
    if A.shape[0] == 0:
        return m, S
    mt, vt, ct = trig_moments(m, S, A)
    sc = S @ ct  # cov[x, trig]
    mean = torch.cat([m, mt], dim=-1)
    cov = torch.cat([torch.cat([S, sc], dim=-1), torch.cat([sc.mT, vt], dim=-1)], dim=-2)
    return mean, cov


def squash_maps(u_max: torch.Tensor, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """``(A, G)`` with ``squash(z) = G sin(A z)``: A ``(J, F)``, G ``(F, J)`` (``F = len(u_max)``)."""
    num_controls = u_max.shape[0]
    eye = torch.eye(num_controls, dtype=u_max.dtype, device=u_max.device)
    if kind == "trapezoid":
        A = torch.cat([eye, 3.0 * eye], dim=0)
        G = torch.cat([9.0 * torch.diag(u_max), torch.diag(u_max)], dim=1) / 8.0
    elif kind == "sin":
        A, G = eye, torch.diag(u_max)
    else:
        raise ValueError(f"unknown squashing {kind!r}; expected one of {SQUASH_KINDS}")
    return A, G


def squash(z: torch.Tensor, u_max: torch.Tensor, kind: str = "trapezoid") -> torch.Tensor:
    """Deterministic squashing of ``z (..., F)`` to ``[-u_max, u_max]``."""
    A, G = squash_maps(u_max, kind)
    return torch.sin(z @ A.T) @ G.T


def squash_moments(
    m: torch.Tensor, S: torch.Tensor, u_max: torch.Tensor, kind: str = "trapezoid", maps=None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact moments of ``squash(z)`` for ``z ~ N(m, S)`` (``m (F,)``, ``S (F, F)``, ``u_max (F,)``).

    ``maps``: ``squash_maps(u_max, kind)`` if already built. Returns mean ``(F,)``, covariance
    ``(F, F)``, ``C (F, F)`` with ``cov[z, u] = S @ C``.
    """
    A, G = squash_maps(u_max, kind) if maps is None else maps
    ms, vs, cs = sin_moments(m, S, A)
    return ms @ G.T, G @ vs @ G.T, cs @ G.T
