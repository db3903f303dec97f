"""Sparse GP regression with shared pseudo-inputs: FITC / SPGP (Snelson & Ghahramani, 2006).

``E`` independent SE-ARD GPs share ``M`` pseudo-inputs ``Z (M, d)``; ``n`` training points
``X (n, d)`` with targets ``Y (n, E)``. Per output ``a`` (kernel hyperparameters as in
:mod:`plugins.pilco.kernels`, noise standard deviation ``sigma_a``)::

    Q_nn   = K_nm K_mm^-1 K_mn
    Lambda = diag(K_nn - Q_nn) + sigma_a^2 I            (the reference's Gamma * sigma_a^2)
    y_a ~ N(0, Q_nn + Lambda)                            (FITC marginal likelihood)

Prediction of the latent ``f`` at a deterministic input ``x`` (``k = k_a(Z, x)``)::

    Q_M    = K_mm + K_mn Lambda^-1 K_nm
    mean   = k^T Q_M^-1 K_mn Lambda^-1 y_a          =: k^T beta_a
    var    = alpha_a^2 - k^T (K_mm^-1 - Q_M^-1) k    =: alpha_a^2 - k^T inv_k_a k

so the FITC model is a :class:`GPPosterior` whose basis inputs are the pseudo-inputs.
All computations go through ``M x M`` Cholesky factors (cost ``O(E n M^2)``); everything is
batched over outputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from plugins.pilco.kernels import cholesky, se_ard
from plugins.pilco.posterior import GPPosterior

#: ridge on K_mm relative to the signal variance alpha_a^2 (the reference adds 1e-6 absolute)
FITC_RIDGE = 1e-6


@dataclass
class FitcFactors:
    """Intermediate FITC quantities, batched over ``E`` outputs.

    Attributes:
        chol_kmm: ``(E, M, M)`` lower Cholesky factor L of ``K_mm + ridge alpha^2 I``.
        lam: ``(E, n)`` diagonal of Lambda (variance units of the targets).
        chol_a: ``(E, M, M)`` lower Cholesky factor of ``A = I + V Lambda^-1 V^T``, ``V = L^-1 K_mn``.
        c: ``(E, M)`` ``chol_a^-1 V Lambda^-1 y``.
        y_white: ``(E, n)`` ``Lambda^-1/2 y``.
    """

    chol_kmm: torch.Tensor
    lam: torch.Tensor
    chol_a: torch.Tensor
    c: torch.Tensor
    y_white: torch.Tensor


def fitc_factors(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    pseudo_inputs: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
    ridge: float = FITC_RIDGE,
) -> FitcFactors:
    """Cholesky-based FITC factors.

    Args:
        inputs: ``(n, d)`` training inputs.
        targets: ``(n, E)`` training targets.
        pseudo_inputs: ``(M, d)`` pseudo-inputs shared by all outputs.
        log_ell, log_alpha, log_sigma: ``(E, d)``, ``(E,)``, ``(E,)`` log-hyperparameters.
        ridge: jitter on ``K_mm`` relative to ``alpha_a^2``.
    """
    num_outputs = log_alpha.shape[0]
    m = pseudo_inputs.shape[0]
    eye = torch.eye(m, dtype=inputs.dtype)
    signal_var = torch.exp(2.0 * log_alpha)  # (E,)
    kmm = se_ard(pseudo_inputs, pseudo_inputs, log_ell, log_alpha) + (ridge * signal_var)[:, None, None] * eye
    kmn = se_ard(pseudo_inputs, inputs, log_ell, log_alpha)  # (E, M, n)
    chol_kmm = cholesky(kmm, "FITC pseudo-input Gram matrix K_mm")
    v = torch.linalg.solve_triangular(chol_kmm, kmn, upper=False)  # (E, M, n)
    q_diag = (v * v).sum(-2)  # (E, n)
    lam = (signal_var[:, None] - q_diag).clamp_min(0.0) + torch.exp(2.0 * log_sigma)[:, None]
    inv_sqrt_lam = torch.rsqrt(lam)
    v_white = v * inv_sqrt_lam[:, None, :]
    a = eye.expand(num_outputs, m, m) + v_white @ v_white.transpose(-1, -2)
    chol_a = cholesky(a, "FITC matrix I + V Lambda^-1 V^T")
    y_white = targets.T * inv_sqrt_lam  # (E, n)
    c = torch.linalg.solve_triangular(chol_a, (v_white @ y_white[..., None]), upper=False)[..., 0]
    return FitcFactors(chol_kmm=chol_kmm, lam=lam, chol_a=chol_a, c=c, y_white=y_white)


def fitc_negative_log_likelihood(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    pseudo_inputs: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
    ridge: float = FITC_RIDGE,
) -> torch.Tensor:
    """FITC negative log marginal likelihood ``-log N(y_a | 0, Q_nn + Lambda)`` per output, ``(E,)``.

    Uses ``log|Q_nn + Lambda| = sum log Lambda + log|A|`` and
    ``y^T (Q_nn + Lambda)^-1 y = y^T Lambda^-1 y - |c|^2`` (matrix determinant lemma, Woodbury).
    Differentiable in all arguments (the pseudo-input gradient drives their optimisation).
    """
    f = fitc_factors(inputs, targets, pseudo_inputs, log_ell, log_alpha, log_sigma, ridge)
    n = inputs.shape[0]
    log_det = torch.log(f.lam).sum(-1) + 2.0 * torch.log(f.chol_a.diagonal(dim1=-2, dim2=-1)).sum(-1)
    quad = (f.y_white**2).sum(-1) - (f.c**2).sum(-1)
    return 0.5 * (quad + log_det + n * math.log(2.0 * math.pi))


def fitc_posterior(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    pseudo_inputs: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
    ridge: float = FITC_RIDGE,
) -> GPPosterior:
    """FITC predictive weights as a :class:`GPPosterior` on the pseudo-inputs.

    With ``Q_M = L A L^T``: ``beta = L^-T chol_a^-T c`` and
    ``inv_k = K_mm^-1 - Q_M^-1 = L^-T (I - A^-1) L^-1`` (symmetrised).
    """
    f = fitc_factors(inputs, targets, pseudo_inputs, log_ell, log_alpha, log_sigma, ridge)
    m = pseudo_inputs.shape[0]
    eye = torch.eye(m, dtype=inputs.dtype).expand(f.chol_a.shape)
    w = torch.linalg.solve_triangular(f.chol_a.transpose(-1, -2), f.c[..., None], upper=True)
    beta = torch.linalg.solve_triangular(f.chol_kmm.transpose(-1, -2), w, upper=True)[..., 0]  # (E, M)
    chol_kmm_inv = torch.linalg.solve_triangular(f.chol_kmm, eye, upper=False)  # L^-1
    middle = eye - torch.cholesky_inverse(f.chol_a)
    inv_k = chol_kmm_inv.transpose(-1, -2) @ middle @ chol_kmm_inv
    inv_k = 0.5 * (inv_k + inv_k.transpose(-1, -2))
    return GPPosterior(
        inputs=pseudo_inputs, beta=beta, inv_k=inv_k, log_ell=log_ell, log_alpha=log_alpha, log_sigma=log_sigma
    )
