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

Large variances: the covariance is evaluated as
``1/2 [exp(l_ij) expm1(Vy_ij) cos(mu_i - mu_j) - exp(l_ij) expm1(-Vy_ij) cos(mu_i + mu_j)]`` with
``l_ij = -(Vy_ii + Vy_jj) / 2`` and each ``exp(l) expm1(v)`` formed without overflow
(:func:`_scaled_expm1`). The textbook product ``e_i e_j expm1(Vy_ij)`` is ``0 * inf = nan`` once
``Vy_ii`` exceeds ~745 (``e_i e_j`` underflows, ``expm1`` overflows at ~710): with the trapezoid
squashing ``Vy`` holds ``9 var[z]``, so a control pre-image variance above ~80 made the control
covariance ``nan`` and the GP's Cholesky then failed ("leading minor of order 1 is not
positive-definite") during policy search on the unicycle; angle variances above ~710 did the same
to ``[sin, cos]`` of the angles (the RBF policy's Cholesky on the cart-double-pendulum). Every factor used here is bounded by 1
for a positive semi-definite ``Vy`` (``|Vy_ij| <= (Vy_ii + Vy_jj) / 2``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

SQUASH_KINDS = ("trapezoid", "sin")
#: slope of each squashing at 0 in units of ``u_max``: trapezoid ``(9 sin z + sin 3z) / 8`` -> (9 + 3) / 8; sin -> 1
SQUASH_SLOPE = {"trapezoid": 1.5, "sin": 1.0}


def _scaled_expm1(log_scale: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``exp(log_scale) * expm1(v)`` without overflow: ``exp(log_scale + v) * -expm1(-v)`` for
    ``v > 0`` (finite while ``log_scale + v <= 0``, as for the sine covariances), else the plain
    product. Equal to the plain product to rounding; exact in relative terms for small ``|v|``.
    Both branches are finite everywhere, so autograd through ``torch.where`` stays finite."""
    positive = v > 0
    up = torch.exp(log_scale + v.clamp(min=0.0)) * -torch.expm1(-v.clamp(min=0.0))
    down = torch.exp(log_scale) * torch.expm1(v.clamp(max=0.0))
    return torch.where(positive, up, down)


def _sin_forward(m, S, A, b):
    """The arithmetic of :func:`sin_moments`; returns the moments and the intermediates.

    With ``l_ij = log(e_i e_j) = -(vy_ii + vy_jj) / 2`` (all four ``(K, K)`` factors are bounded
    by 1/2 in magnitude for a positive semi-definite ``vy``; see the module docstring)::

        P = e_i e_j expm1(vy_ij) / 2,   N = e_i e_j expm1(-vy_ij) / 2,
        Ep = e_i e_j exp(vy_ij) / 2,    En = e_i e_j exp(-vy_ij) / 2,
        cov = P cos(mu_i - mu_j) - N cos(mu_i + mu_j).
    """
    mu = m @ A.T
    if b is not None:
        mu = mu + b
    vy = A @ S @ A.T  # (..., K, K)
    half_v = 0.5 * torch.diagonal(vy, dim1=-2, dim2=-1)  # (..., K)
    e = torch.exp(-half_v)  # (..., K)
    s, c = torch.sin(mu), torch.cos(mu)
    diff = mu[..., :, None] - mu[..., None, :]
    summ = mu[..., :, None] + mu[..., None, :]
    cos_d, cos_s = torch.cos(diff), torch.cos(summ)
    log_ee = -(half_v[..., :, None] + half_v[..., None, :])  # (..., K, K)
    P = 0.5 * _scaled_expm1(log_ee, vy)
    N = 0.5 * _scaled_expm1(log_ee, -vy)
    Ep = 0.5 * torch.exp(log_ee + vy)
    En = 0.5 * torch.exp(log_ee - vy)
    cov = P * cos_d - N * cos_s
    ec = e * c
    moments = (e * s, cov, A.T * ec[..., None, :])
    return moments, (s, c, e, diff, summ, cos_d, cos_s, P, N, Ep, En, cov)


def _sin_backward(A, saved, g_mean, g_cov, g_cross, need_m=True, need_S=True):
    """Hand-derived gradients of :func:`_sin_forward` wrt ``(m, S)`` (``A``, ``b`` fixed).

    ``saved``: the intermediates from :func:`_sin_forward`; ``g_*``: gradients wrt the three
    moments (``None`` for zero). Returns ``(g_m, g_S)`` (``None`` where not needed).
    """
    s, c, e, diff, summ, cos_d, cos_s, P, N, Ep, En, cov = saved
    # gradients wrt mu, log e (= -vy_ii / 2) and vy; log e rather than e keeps every product finite
    g_loge = torch.zeros_like(e)
    g_mu = torch.zeros_like(e)
    g_vy = torch.zeros_like(cov)
    if g_cov is not None:
        # cov_ij = 1/2 e_i e_j [expm1(v_ij) cos(mu_i - mu_j) - expm1(-v_ij) cos(mu_i + mu_j)]
        g_vy = g_cov * (Ep * cos_d + En * cos_s)
        n_ss = N * torch.sin(summ)
        p_sd = P * torch.sin(diff)
        g_mu = (g_cov * (n_ss - p_sd)).sum(-1) + (g_cov * (n_ss + p_sd)).sum(-2)
        gc = g_cov * cov  # cov_ij is proportional to e_i e_j
        g_loge = gc.sum(-1) + gc.sum(-2)
    if g_mean is not None:  # mean = e sin mu
        g_loge = g_loge + g_mean * e * s
        g_mu = g_mu + g_mean * e * c
    if g_cross is not None:  # cross = A^T diag(e cos mu)
        g_ec = (g_cross * A.T).sum(-2)
        g_loge = g_loge + g_ec * e * c
        g_mu = g_mu - g_ec * e * s
    # log e = -vy_ii / 2,  vy = A S A^T,  mu = A m + b
    g_vy = g_vy - torch.diag_embed(0.5 * g_loge)
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
    offset = torch.cat([A.new_zeros(k), A.new_full((k,), 0.5 * math.pi)])
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
