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
    eye = torch.eye(m, dtype=inputs.dtype, device=inputs.device)
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
    eye = torch.eye(m, dtype=inputs.dtype, device=inputs.device).expand(f.chol_a.shape)
    w = torch.linalg.solve_triangular(f.chol_a.transpose(-1, -2), f.c[..., None], upper=True)
    beta = torch.linalg.solve_triangular(f.chol_kmm.transpose(-1, -2), w, upper=True)[..., 0]  # (E, M)
    chol_kmm_inv = torch.linalg.solve_triangular(f.chol_kmm, eye, upper=False)  # L^-1
    middle = eye - torch.cholesky_inverse(f.chol_a)
    inv_k = chol_kmm_inv.transpose(-1, -2) @ middle @ chol_kmm_inv
    inv_k = 0.5 * (inv_k + inv_k.transpose(-1, -2))
    return GPPosterior(
        inputs=pseudo_inputs, beta=beta, inv_k=inv_k, log_ell=log_ell, log_alpha=log_alpha, log_sigma=log_sigma
    )


#: residual variance (relative to the unit signal variance) below which a basis point counts as explained
EXPLAINED = 1e-10


def select_basis(basis: torch.Tensor, inputs: torch.Tensor, log_ell: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` of the ``M`` basis inputs that explain the kernel at the training inputs best (greedy).

    Each step takes the basis point that most reduces ``sum_a sum_i (k_a(x_i, x_i) - Q_a,ii) / alpha_a^2``,
    the part of the prior variance at the training inputs that the chosen basis does not explain
    (FITC's ``Lambda - sigma^2``; the Nystroem error of Smola & Schoelkopf's sparse greedy matrix
    approximation): ``gain_j = sum_a |r_a,j|^2 / d_a,j`` with ``r_a,j`` the residual covariance between the
    data and basis point ``j`` and ``d_a,j`` its residual variance, both given the points taken so far
    (rank-one updates of a partial Cholesky factor). Unlike spreading the points over the kernel's
    geometry it keeps them where the data are. Deterministic, ``O(E n M count)``.

    Args:
        basis: ``(M, d)`` basis inputs (FITC pseudo-inputs, or a full GP's training inputs).
        inputs: ``(n, d)`` training inputs.
        log_ell: ``(E, d)`` log length-scales.
        count: how many to keep, ``1 <= count <= M``.

    Returns:
        ``(count,)`` long indices into ``basis`` in the order taken.
    """
    m = basis.shape[0]
    if not 1 <= count <= m:
        raise ValueError(f"select_basis: count={count} must be between 1 and the {m} basis inputs")
    zeros = torch.zeros(log_ell.shape[0], dtype=basis.dtype, device=basis.device)
    gram = se_ard(basis, basis, log_ell, zeros)  # (E, M, M), unit signal variance
    residual = se_ard(inputs, basis, log_ell, zeros)  # (E, n, M): data-basis covariance given the points taken
    variance = gram.diagonal(dim1=-2, dim2=-1).clone()  # (E, M): residual variance of each basis point
    factor = basis.new_zeros(log_ell.shape[0], m, count)  # partial Cholesky factor over the basis
    taken = torch.zeros(m, dtype=torch.bool, device=basis.device)
    chosen = []
    for k in range(count):
        # an output for which a point is already explained (residual variance ~ rounding) gains nothing from it
        live = variance > EXPLAINED
        gain = torch.where(live, (residual * residual).sum(1) / torch.where(live, variance, 1.0), 0.0).sum(0)  # (M,)
        gain[taken] = -1.0  # never taken twice (a duplicate of a taken point gains nothing either)
        j = int(torch.argmax(gain))
        chosen.append(j)
        taken[j] = True
        ok = live[:, j, None]  # (E, 1)
        scale = torch.where(ok, variance[:, j, None], 1.0).sqrt()
        column = torch.where(ok, (gram[:, :, j] - (factor[:, :, :k] @ factor[:, j, :k, None])[..., 0]) / scale, 0.0)  # (E, M)
        data_column = torch.where(ok, residual[:, :, j] / scale, 0.0)  # (E, n)
        factor[:, :, k] = column
        residual -= data_column[:, :, None] * column[:, None, :]
        variance = (variance - column * column).clamp_min(0.0)
    return torch.tensor(chosen, dtype=torch.long, device=basis.device)


def reduced_posterior(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    basis: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
    count: int,
    ridge: float = FITC_RIDGE,
) -> GPPosterior:
    """A FITC posterior on ``count`` of the model's basis inputs, for cheaper planning.

    The basis inputs are chosen by :func:`select_basis` (where the data are); the hyperparameters and
    the training data are the model's own, so only the basis shrinks. Moment matching's cost per step grows with the
    square of the basis size, so half the basis is about a quarter of the planning arithmetic; what
    it costs in model quality is measured by ``benchmarks/planning_basis_check.py``.

    Args:
        inputs, targets: ``(n, d)``, ``(n, E)`` training data.
        basis: ``(M, d)`` the model's basis (pseudo-inputs, or a full GP's training inputs).
        log_ell, log_alpha, log_sigma: the model's log-hyperparameters.
        count: basis points kept, ``1 <= count <= M``.
    """
    keep = select_basis(basis, inputs, log_ell, count)
    return fitc_posterior(inputs, targets, basis[keep], log_ell, log_alpha, log_sigma, ridge)


def fitc_nll_and_pseudo_gradient(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    pseudo_inputs: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
    ridge: float = FITC_RIDGE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`fitc_negative_log_likelihood` ``(E,)`` and its gradient wrt the pseudo-inputs, per
    output ``(E, M, d)``, by hand (hyperparameters fixed; what the pseudo-input optimisation needs).

    With ``Sigma = Q_nn + Lambda``, ``a = Sigma^-1 y`` and ``W = Sigma^-1 - a a^T``, the NLL's
    differential is ``1/2 tr(W~ dQ_nn)``, where ``W~`` is ``W`` minus the diagonal that ``Lambda``
    takes back (``Lambda_ii = alpha^2 - Q_ii + sigma^2`` where not clamped at 0, mask ``m``)::

        dNLL/dK_mn = B W~,   dNLL/dK_mm = -1/2 B W~ B^T,   B = K_mm^-1 K_mn.

    In the forward pass's factors (``K_mm = L L^T``, ``V = L^-1 K_mn``, ``s = Lambda^-1/2``,
    ``A = I + V diag(s^2) V^T = L_A L_A^T``, ``R = L_A^-1 V diag(s)``) and with Woodbury
    (``B Sigma^-1 = L^-T A^-1 V Lambda^-1``)::

        a        = s (y s - R^T c),           diag(Sigma^-1) = s^2 (1 - colsum(R^2))
        D        = m (diag(Sigma^-1) - a^2)
        dNLL/dK_mn = L^-T [L_A^-T R diag(s) - (V a) a^T - V diag(D)]
        dNLL/dK_mm = -1/2 L^-T [I - A^-1 - (V a)(V a)^T - V diag(D) V^T] L^-1

    and the SE kernel's derivative takes both to ``Z``. About 6 ``M^2 n`` multiply-adds per output
    against ~12 for autograd through the same forward pass (measured 0.46 -> see
    benchmarks/bench_gp_fit.py --fitc); tested equal to autograd to 1e-10.
    """
    num_outputs, n = log_alpha.shape[0], inputs.shape[0]
    m = pseudo_inputs.shape[0]
    eye = torch.eye(m, dtype=inputs.dtype, device=inputs.device)
    signal_var = torch.exp(2.0 * log_alpha)  # (E,)
    # The (E, M, n) matrices (10-100 MB here) are held transposed, (E, n, M) row-major: LAPACK's
    # triangular solves then work on them in place (solving from the right) instead of on copies,
    # and elementwise work is done in place.
    kmm0 = se_ard(pseudo_inputs, pseudo_inputs, log_ell, log_alpha)  # (E, M, M), no ridge
    kmn_t = _se_ard_inplace(inputs, pseudo_inputs, log_ell, log_alpha)  # (E, n, M) = K_mn^T
    chol_kmm = cholesky(kmm0 + (ridge * signal_var)[:, None, None] * eye, "FITC pseudo-input Gram matrix K_mm")
    v_t = torch.linalg.solve_triangular(chol_kmm.mT, kmn_t, upper=True, left=False)  # V^T = K_nm L^-T
    q_diag = torch.linalg.vector_norm(v_t, dim=-1).square_()  # (E, n)
    free = signal_var[:, None] - q_diag
    mask = (free > 0).to(inputs.dtype)
    lam = free.clamp_min(0.0) + torch.exp(2.0 * log_sigma)[:, None]
    s = torch.rsqrt(lam)  # (E, n)
    vw_t = v_t * s[..., None]
    a_mat = torch.baddbmm(eye.expand(num_outputs, m, m), vw_t.mT, vw_t)
    chol_a = cholesky(a_mat, "FITC matrix I + V Lambda^-1 V^T")
    y_white = targets.T * s  # (E, n)
    r_t = torch.linalg.solve_triangular(chol_a.mT, vw_t, upper=True, left=False)  # R^T = (L_A^-1 V diag(s))^T
    del vw_t
    c = (r_t.mT @ y_white[..., None])[..., 0]  # (E, M)
    log_det = torch.log(lam).sum(-1) + 2.0 * torch.log(chol_a.diagonal(dim1=-2, dim2=-1)).sum(-1)
    nll = 0.5 * ((y_white**2).sum(-1) - (c**2).sum(-1) + log_det + n * math.log(2.0 * math.pi))

    a_vec = s * (y_white - (r_t @ c[..., None])[..., 0])  # (E, n) Sigma^-1 y
    diag_w = mask * (s * s * (1.0 - torch.linalg.vector_norm(r_t, dim=-1).square_()) - a_vec * a_vec)  # (E, n)
    va = (v_t.mT @ a_vec[..., None])[..., 0]  # (E, M)
    vd_t = v_t * diag_w[..., None]
    inner = torch.baddbmm(eye - torch.cholesky_inverse(chol_a), v_t.mT, vd_t, alpha=-1.0)
    inner.sub_(va[..., None] * va[:, None, :])
    # h^T = diag(s) R^T L_A^-1 - a (V a)^T - diag(D) V^T
    h_t = torch.linalg.solve_triangular(chol_a, r_t, upper=False, left=False).mul_(s[..., None])
    del r_t
    h_t.sub_(vd_t).baddbmm_(a_vec[..., None], va[:, None, :], alpha=-1.0)
    del vd_t, v_t
    g_kmn_t = torch.linalg.solve_triangular(chol_kmm, h_t, upper=False, left=False)  # (dNLL/dK_mn)^T = h^T L^-1
    del h_t
    # dNLL/dK_mm = -1/2 L^-T inner L^-1 by two triangular solves (M^3 / 2 multiply-adds each), not by forming
    # L^-1 and two M x M products (M^3 / 6 + 2 M^3)
    g_kmm = torch.linalg.solve_triangular(chol_kmm, inner, upper=False, left=False)  # inner L^-1
    g_kmm = torch.linalg.solve_triangular(chol_kmm.mT, g_kmm, upper=True).mul_(-0.5)  # (E, M, M), symmetric

    # SE kernel: dk(z_j, x_i)/dz_j = k (x_i - z_j) / ell^2; K_mm has z in both places (factor 2, symmetric)
    inv_ell2 = torch.exp(-2.0 * log_ell)[:, None, :]  # (E, 1, d)
    t1_t = g_kmn_t.mul_(kmn_t)  # (E, n, M)
    t2 = g_kmm * kmm0
    grad = (t1_t.mT @ inputs - t1_t.sum(-2)[..., None] * pseudo_inputs) * inv_ell2
    grad = grad + 2.0 * (t2 @ pseudo_inputs - t2.sum(-1, keepdim=True) * pseudo_inputs) * inv_ell2
    return nll, grad


def _se_ard_inplace(x1: torch.Tensor, x2: torch.Tensor, log_ell: torch.Tensor, log_alpha: torch.Tensor) -> torch.Tensor:
    """:func:`~plugins.pilco.kernels.se_ard` for shared ``x1 (n, d)``, ``x2 (m, d)`` with one
    ``(E, n, m)`` buffer updated in place (no autograd)."""
    inv_ell = torch.exp(-log_ell)[:, None, :]  # (E, 1, d)
    a, b = x1 * inv_ell, x2 * inv_ell  # (E, n, d), (E, m, d)
    sq = torch.baddbmm((a * a).sum(-1)[:, :, None] + (b * b).sum(-1)[:, None, :], a, b.transpose(-1, -2), alpha=-2.0)
    return sq.clamp_min_(0.0).mul_(-0.5).add_(2.0 * log_alpha[:, None, None]).exp_()


class _FitcNLLPseudo(torch.autograd.Function):
    """``fitc_negative_log_likelihood`` as a function of the pseudo-inputs alone, with the gradient of
    :func:`fitc_nll_and_pseudo_gradient` (computed in the forward pass: the optimiser always asks for it)."""

    @staticmethod
    def forward(ctx, pseudo_inputs, inputs, targets, log_ell, log_alpha, log_sigma, ridge):
        nll, grad = fitc_nll_and_pseudo_gradient(inputs, targets, pseudo_inputs, log_ell, log_alpha, log_sigma, ridge)
        ctx.save_for_backward(grad)
        return nll

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_nll):
        (grad,) = ctx.saved_tensors
        return (g_nll[:, None, None] * grad).sum(0), None, None, None, None, None, None


def fitc_nll_of_pseudo_inputs(inputs, targets, pseudo_inputs, log_ell, log_alpha, log_sigma, ridge: float = FITC_RIDGE) -> torch.Tensor:
    """FITC NLL per output ``(E,)``, differentiable wrt ``pseudo_inputs`` only (hand-derived gradient;
    the hyperparameters are taken as constants)."""
    return _FitcNLLPseudo.apply(pseudo_inputs, inputs.detach(), targets.detach(), log_ell.detach(), log_alpha.detach(),
                                log_sigma.detach(), ridge)
