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


def _sin_forward(m, S, A, b):
    """The arithmetic of :func:`sin_moments`; returns the moments and the intermediates."""
    mu = m @ A.T
    if b is not None:
        mu = mu + b
    vy = A @ S @ A.T  # (..., K, K)
    e = torch.exp(-0.5 * torch.diagonal(vy, dim1=-2, dim2=-1))  # (..., K)
    s, c = torch.sin(mu), torch.cos(mu)
    diff = mu[..., :, None] - mu[..., None, :]
    summ = mu[..., :, None] + mu[..., None, :]
    cos_d, cos_s = torch.cos(diff), torch.cos(summ)
    pos, neg = torch.expm1(vy), torch.expm1(-vy)
    half_ee = 0.5 * e[..., :, None] * e[..., None, :]
    inner = pos * cos_d - neg * cos_s
    ec = e * c
    moments = (e * s, half_ee * inner, A.T * ec[..., None, :])
    return moments, (s, c, e, diff, summ, cos_d, cos_s, pos, neg, half_ee, inner)


def _sin_backward(A, saved, g_mean, g_cov, g_cross, need_m=True, need_S=True):
    """Hand-derived gradients of :func:`_sin_forward` wrt ``(m, S)`` (``A``, ``b`` fixed).

    ``saved``: the intermediates from :func:`_sin_forward`; ``g_*``: gradients wrt the three
    moments (``None`` for zero). Returns ``(g_m, g_S)`` (``None`` where not needed).
    """
    s, c, e, diff, summ, cos_d, cos_s, pos, neg, half_ee, inner = saved
    g_e = torch.zeros_like(e)
    g_mu = torch.zeros_like(e)
    g_vy = torch.zeros_like(inner)
    if g_cov is not None:
        # cov_ij = 1/2 e_i e_j [expm1(v_ij) cos(mu_i - mu_j) - expm1(-v_ij) cos(mu_i + mu_j)]
        gh = g_cov * half_ee
        g_vy = gh * ((pos + 1.0) * cos_d + (neg + 1.0) * cos_s)
        p_sd = pos * torch.sin(diff)
        n_ss = neg * torch.sin(summ)
        g_mu = (gh * (n_ss - p_sd)).sum(-1) + (gh * (n_ss + p_sd)).sum(-2)
        gi = 0.5 * g_cov * inner
        g_e = (gi * e[..., None, :]).sum(-1) + (gi * e[..., :, None]).sum(-2)
    if g_mean is not None:  # mean = e sin mu
        g_e = g_e + g_mean * s
        g_mu = g_mu + g_mean * e * c
    if g_cross is not None:  # cross = A^T diag(e cos mu)
        g_ec = (g_cross * A.T).sum(-2)
        g_e = g_e + g_ec * c
        g_mu = g_mu - g_ec * e * s
    # e = exp(-vy_ii / 2),  vy = A S A^T,  mu = A m + b
    g_vy = g_vy - torch.diag_embed(0.5 * e * g_e)
    g_S = A.T @ g_vy @ A if need_S else None
    g_m = g_mu @ A if need_m else None
    return g_m, g_S


class _SinMoments(torch.autograd.Function):
    """:func:`sin_moments` with a hand-derived backward pass (wrt ``m`` and ``S``; ``A``, ``b`` fixed)."""

    @staticmethod
    def forward(ctx, m, S, A, b):
        moments, saved = _sin_forward(m, S, A, b)
        ctx.A, ctx.saved = A, saved
        return moments

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_mean, g_cov, g_cross):
        needs = ctx.needs_input_grad
        g_m, g_S = _sin_backward(ctx.A, ctx.saved, g_mean, g_cov, g_cross, needs[0], needs[1])
        return g_m, g_S, None, None


def sin_moments(
    m: torch.Tensor, S: torch.Tensor, A: torch.Tensor, b: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``sin(A x + b)`` for ``x ~ N(m, S)``.

    Args:
        m: ``(..., D)``; S: ``(..., D, D)``; A: ``(K, D)``; b: ``(K,)`` or ``None`` (zero).
        ``A`` and ``b`` are constants (no gradients).

    Returns:
        mean ``(..., K)``, covariance ``(..., K, K)``, ``C (..., D, K)`` with ``cov[x, sin y] = S @ C``.
    """
    if torch.is_grad_enabled() and (m.requires_grad or S.requires_grad):
        return _SinMoments.apply(m, S, A, b)
    return _sin_forward(m, S, A, b)[0]


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
