"""Squared-exponential ARD kernel and guarded Cholesky factorisation (float64 torch).

Conventions used throughout ``plugins.pilco``:

* ``E`` outputs (one GP per output), ``n`` training points, ``d`` input dimensions.
* SE-ARD kernel  k_a(x, x') = alpha_a^2 exp(-1/2 (x - x')^T Lambda_a^-1 (x - x')),
  Lambda_a = diag(ell_a^2); parameters are stored as logs: ``log_ell (E, d)``, ``log_alpha (E,)``.
"""

from __future__ import annotations

import torch

from harness.errors import NumericalError

#: jitter added on the diagonal, escalating by x10 per retry
JITTER_START = 1e-9
JITTER_RETRIES = 7


def se_ard(x1: torch.Tensor, x2: torch.Tensor, log_ell: torch.Tensor, log_alpha: torch.Tensor) -> torch.Tensor:
    """Batched SE-ARD Gram matrices.

    Args:
        x1: ``(n, d)`` or ``(E, n, d)``.
        x2: ``(m, d)`` or ``(E, m, d)``.
        log_ell: ``(E, d)`` log length-scales.
        log_alpha: ``(E,)`` log signal standard deviations.

    Returns:
        ``(E, n, m)`` with ``K[a, i, j] = k_a(x1_i, x2_j)``.
    """
    inv_ell = torch.exp(-log_ell)  # (E, d)
    a = x1 * inv_ell[:, None, :]  # (E, n, d), broadcasting a shared (n, d)
    b = x2 * inv_ell[:, None, :]  # (E, m, d)
    sq = (a * a).sum(-1)[:, :, None] + (b * b).sum(-1)[:, None, :] - 2.0 * a @ b.transpose(-1, -2)
    sq = sq.clamp_min(0.0)
    return torch.exp(2.0 * log_alpha)[:, None, None] * torch.exp(-0.5 * sq)


def cholesky(matrix: torch.Tensor, what: str = "matrix") -> torch.Tensor:
    """Lower Cholesky factor of a (batch of) symmetric positive-definite matrices.

    Tries the plain factorisation, then adds jitter ``1e-9 * mean(diag)``, escalating by x10 up to
    ``1e-3 * mean(diag)``. Raises :class:`NumericalError` naming ``what`` if all attempts fail.
    Differentiable (the jitter is treated as a constant).
    """
    chol, info = torch.linalg.cholesky_ex(matrix)
    if not bool(torch.any(info)):
        return chol
    eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype, device=matrix.device)
    scale = matrix.diagonal(dim1=-2, dim2=-1).mean(-1).abs().clamp_min(1e-12).detach()
    jitter = JITTER_START
    for _ in range(JITTER_RETRIES):
        chol, info = torch.linalg.cholesky_ex(matrix + (jitter * scale)[..., None, None] * eye)
        if not bool(torch.any(info)):
            return chol
        jitter *= 10.0
    raise NumericalError(
        f"Cholesky of the {what} failed even with jitter {jitter / 10:.0e} x mean diagonal; "
        "the data are degenerate (duplicated inputs with zero noise?) - raise the noise floor"
    )
