"""PILCO's GP dynamics model (paper §2.1): E independent SE-ARD GPs trained by evidence maximisation.

Shapes: ``n`` training points, ``d`` input dimensions, ``E`` outputs (one GP each), ``m`` test
points, ``M`` pseudo-inputs. Inputs ``X (n, d)``, targets ``Y (n, E)`` (the learner passes state
differences; this module just regresses). Hyperparameters are stored as logs:
``log_ell (E, d)``, ``log_alpha (E,)`` (signal std), ``log_sigma (E,)`` (noise std).

Training follows the reference (``gp/train.m``, ``gp/hypCurb.m``, ``gp/fitc.m``):

* objective per output = negative log marginal likelihood + hypCurb penalty
  ``sum_d ((log ell_d - log s_d)/log 100)^30 + ((log alpha - log sigma)/log 1000)^30`` with
  ``s`` the input standard deviations (a soft box: ell within ~[s/100, 100 s], SNR below ~1000);
* L-BFGS-B (scipy) on the sum over outputs (as the reference: one joint run), all outputs
  batched, with the analytic NLL gradient (custom autograd backward, ~2x faster than autograd
  through the Cholesky factor); measured slightly faster than ``torch.optim.LBFGS`` (strong Wolfe)
  on the same objective (benchmarks/bench_gp_fit.py);
* noise floor: ``sigma_a >= max(1e-4 * scale(y_a), 1e-8)`` enforced as an L-BFGS-B bound
  (``scale`` = std of the targets, falling back to their RMS, then 1, for constant targets);
* initialisation without warm start: ``log ell = log s``, ``log alpha = log scale(y)``,
  ``log sigma = log(scale(y)/10)``; optional seeded restarts perturb it, the best run per output
  (by penalised NLL; the outputs are independent GPs) is kept;
* above ``sparse_threshold`` points, FITC with ``M`` shared pseudo-inputs takes over: the
  hyperparameters are trained as a full GP on a random subset of at most ``hyper_subset`` points
  (bounding the O(n^3) cost; the reference uses all points), then only the pseudo-inputs are
  optimised on the FITC NLML (first time from a random subset of the inputs, later warm-started).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.optimize
import torch
from threadpoolctl import threadpool_limits

from harness.errors import NumericalError
from plugins.pilco.kernels import cholesky, se_ard
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.sparse import (FITC_RIDGE, fitc_negative_log_likelihood, fitc_nll_of_pseudo_inputs, fitc_posterior,
                                  reduced_posterior)

DTYPE = torch.float64
#: hypCurb: length-scales within ~100x of the input std, signal-to-noise ratio below ~1000, power 30
CURB_LOG_LS = math.log(100.0)
CURB_LOG_SNR = math.log(1000.0)
CURB_POWER = 30
#: noise floor sigma_a >= max(NOISE_FLOOR_REL * scale(y_a), NOISE_FLOOR_ABS)
NOISE_FLOOR_REL = 1e-4
NOISE_FLOOR_ABS = 1e-8
#: L-BFGS-B box (far outside the hypCurb box, only there to keep trial points finite)
_BOX_LOG_ELL = 3.0 * CURB_LOG_LS
_BOX_LOG_AMPLITUDE = 3.0 * CURB_LOG_SNR


@dataclass
class GPHyperparameters:
    """Log-hyperparameters of ``E`` GPs, plus the FITC pseudo-inputs when the model is sparse.

    Attributes:
        log_ell: ``(E, d)`` log length-scales (input units).
        log_alpha: ``(E,)`` log signal standard deviations (target units).
        log_sigma: ``(E,)`` log noise standard deviations (target units).
        pseudo_inputs: ``(M, d)`` shared FITC pseudo-inputs, or ``None`` for a full GP.
    """

    log_ell: torch.Tensor
    log_alpha: torch.Tensor
    log_sigma: torch.Tensor
    pseudo_inputs: torch.Tensor | None = None

    def to(self, device: torch.device | str) -> "GPHyperparameters":
        """A copy on ``device``."""
        z = None if self.pseudo_inputs is None else self.pseudo_inputs.detach().to(device).clone()
        return GPHyperparameters(*(t.detach().to(device).clone() for t in (self.log_ell, self.log_alpha, self.log_sigma)), z)

    def clone(self) -> "GPHyperparameters":
        z = None if self.pseudo_inputs is None else self.pseudo_inputs.detach().clone()
        return GPHyperparameters(
            self.log_ell.detach().clone(), self.log_alpha.detach().clone(), self.log_sigma.detach().clone(), z
        )

    def as_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors for checkpoints (``torch.load(weights_only=True)``); no key for absent pseudo-inputs."""
        out = {"log_ell": self.log_ell, "log_alpha": self.log_alpha, "log_sigma": self.log_sigma}
        if self.pseudo_inputs is not None:
            out["pseudo_inputs"] = self.pseudo_inputs
        return {k: v.detach().clone() for k, v in out.items()}

    @classmethod
    def from_dict(cls, state: dict) -> "GPHyperparameters":
        """Inverse of :meth:`as_dict`."""
        z = state.get("pseudo_inputs")
        return cls(
            *(torch.as_tensor(state[k], dtype=DTYPE).clone() for k in ("log_ell", "log_alpha", "log_sigma")),
            None if z is None else torch.as_tensor(z, dtype=DTYPE).clone(),
        )


# ----------------------------------------------------------------------------- data scales


def _robust_scale(values: torch.Tensor) -> torch.Tensor:
    """Per-column spread of ``values (n, k)``: std, else RMS (constant non-zero column), else 1."""
    std = values.std(dim=0, unbiased=True) if values.shape[0] > 1 else values.new_zeros(values.shape[1])
    rms = values.pow(2).mean(0).sqrt()
    degenerate_std = std <= 1e-10 * (1.0 + rms)
    fallback = torch.where(rms > 0, rms, torch.ones_like(rms))
    return torch.where(degenerate_std, fallback, std)


def input_scale(inputs: torch.Tensor) -> torch.Tensor:
    """``(d,)`` standard deviations of the inputs ``(n, d)`` (hypCurb's ``s``).

    A constant input column gets its RMS (or 1 if it is zero), so ``log s`` stays finite.
    """
    return _robust_scale(inputs)


def target_scale(targets: torch.Tensor) -> torch.Tensor:
    """``(E,)`` standard deviations of the targets ``(n, E)``, with the same constant-column fallback."""
    return _robust_scale(targets)


def noise_floor(targets: torch.Tensor, rel: float = NOISE_FLOOR_REL, abs_: float = NOISE_FLOOR_ABS) -> torch.Tensor:
    """``(E,)`` lowest allowed noise standard deviation: ``max(rel * scale(y_a), abs_)``."""
    return torch.clamp_min(rel * target_scale(targets), abs_)


def initial_hyperparameters(inputs: torch.Tensor, targets: torch.Tensor) -> GPHyperparameters:
    """The reference's initialisation: ``ell_d = s_d``, ``alpha = scale(y)``, ``sigma = scale(y)/10``."""
    num_outputs = targets.shape[1]
    log_s = torch.log(input_scale(inputs))
    log_y = torch.log(target_scale(targets))
    return GPHyperparameters(
        log_ell=log_s.expand(num_outputs, -1).clone(), log_alpha=log_y.clone(), log_sigma=log_y - math.log(10.0)
    )


# ----------------------------------------------------------------------------- objective


def hyp_curb_penalty(
    log_ell: torch.Tensor, log_alpha: torch.Tensor, log_sigma: torch.Tensor, input_std: torch.Tensor
) -> torch.Tensor:
    """hypCurb penalty per output, ``(E,)`` (dimensionless, added to the NLL).

    ``sum_d ((log ell_ad - log s_d)/log 100)^30 + ((log alpha_a - log sigma_a)/log 1000)^30``;
    ``input_std`` is ``s (d,)``.
    """
    ls_term = ((log_ell - torch.log(input_std)[None, :]) / CURB_LOG_LS).pow(CURB_POWER).sum(-1)
    snr_term = ((log_alpha - log_sigma) / CURB_LOG_SNR).pow(CURB_POWER)
    return ls_term + snr_term


def _noisy_gram_cholesky(
    inputs: torch.Tensor, log_ell: torch.Tensor, log_alpha: torch.Tensor, log_sigma: torch.Tensor
) -> torch.Tensor:
    """``(E, n, n)`` lower Cholesky factors of ``K_a + sigma_a^2 I``."""
    n = inputs.shape[0]
    gram = se_ard(inputs, inputs, log_ell, log_alpha)
    noise = torch.exp(2.0 * log_sigma)[:, None, None] * torch.eye(n, dtype=inputs.dtype, device=inputs.device)
    return cholesky(gram + noise, "GP Gram matrix K + sigma^2 I")


class _NegLogMarginalLikelihood(torch.autograd.Function):
    """Batched GP NLL with the analytic hyperparameter gradient (Rasmussen & Williams eq. 5.9).

    With ``W_a = (K_a + sigma_a^2 I)^-1 - b_a b_a^T``, ``b_a = (K_a + sigma_a^2 I)^-1 y_a`` and the
    noise-free Gram matrix ``F_a``, ``P_a = W_a o F_a`` (elementwise)::

        d nll_a / d log ell_ad = (sum_i x_id^2 (P_a 1)_i - x_d^T P_a x_d) / ell_ad^2
        d nll_a / d log alpha_a = sum_ij P_aij
        d nll_a / d log sigma_a = sigma_a^2 tr W_a

    About twice as fast as autograd through the Cholesky factorisation. No gradient with respect
    to the data.
    """

    @staticmethod
    def forward(ctx, inputs, targets, log_ell, log_alpha, log_sigma):  # type: ignore[override]
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            raise ValueError("negative_log_marginal_likelihood has no gradient with respect to the data")
        n = inputs.shape[0]
        gram_f = se_ard(inputs, inputs, log_ell, log_alpha)  # (E, n, n)
        noise_var = torch.exp(2.0 * log_sigma)  # (E,)
        eye = torch.eye(n, dtype=inputs.dtype, device=inputs.device)
        chol = cholesky(gram_f + noise_var[:, None, None] * eye, "GP Gram matrix K + sigma^2 I")
        b = torch.cholesky_solve(targets.T[..., None], chol)[..., 0]  # (E, n)
        log_det = 2.0 * torch.log(chol.diagonal(dim1=-2, dim2=-1)).sum(-1)
        ctx.save_for_backward(inputs, log_ell, gram_f, chol, b, noise_var)
        return 0.5 * ((targets.T * b).sum(-1) + log_det + n * math.log(2.0 * math.pi))

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        inputs, log_ell, gram_f, chol, b, noise_var = ctx.saved_tensors
        w = torch.cholesky_inverse(chol) - b[:, :, None] * b[:, None, :]  # (E, n, n)
        p = w * gram_f
        row = p.sum(-1)  # (E, n)
        quad = (inputs[None] * (p @ inputs)).sum(1)  # (E, d): x_d^T P x_d
        g_ell = (row @ inputs.pow(2) - quad) * torch.exp(-2.0 * log_ell)
        g_alpha = p.sum((-1, -2))
        g_sigma = noise_var * w.diagonal(dim1=-2, dim2=-1).sum(-1)
        return None, None, grad_out[:, None] * g_ell, grad_out * g_alpha, grad_out * g_sigma


def negative_log_marginal_likelihood(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
) -> torch.Tensor:
    """``-log N(y_a | 0, K_a + sigma_a^2 I)`` for every output, ``(E,)`` (nats).

    Differentiable in the log-hyperparameters (analytic gradient), not in the data.

    Args:
        inputs: ``(n, d)``; targets: ``(n, E)``; log-hyperparameters ``(E, d)``, ``(E,)``, ``(E,)``.
    """
    return _NegLogMarginalLikelihood.apply(inputs, targets, log_ell, log_alpha, log_sigma)


def full_posterior(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    log_ell: torch.Tensor,
    log_alpha: torch.Tensor,
    log_sigma: torch.Tensor,
) -> GPPosterior:
    """Full-GP :class:`GPPosterior`: ``beta = (K + sigma^2 I)^-1 y``, ``inv_k = (K + sigma^2 I)^-1``."""
    chol = _noisy_gram_cholesky(inputs, log_ell, log_alpha, log_sigma)
    beta = torch.cholesky_solve(targets.T[..., None], chol)[..., 0]  # (E, n)
    inv_k = torch.cholesky_inverse(chol)
    return GPPosterior(inputs=inputs, beta=beta, inv_k=inv_k, log_ell=log_ell, log_alpha=log_alpha, log_sigma=log_sigma)


def predict_latent(posterior: GPPosterior, test_inputs: torch.Tensor, fused: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Predictive mean and latent variance (no observation noise) at deterministic inputs.

    Args:
        posterior: full or FITC posterior with ``n`` basis inputs.
        test_inputs: ``(m, d)``.
        fused: where no tensor of the posterior requires grad, compute in one pass with a closed-form
            gradient wrt ``test_inputs`` (:class:`_PredictLatent`); ``False``: the torch composition,
            differentiated by autograd (the reference the fused pass is tested against).

    Returns:
        ``mean (m, E)`` and ``var (m, E)`` (target units and their squares), from
        ``mean_a = beta_a . k_a(x)``, ``var_a = alpha_a^2 - k_a(x)^T inv_k_a k_a(x)``.
    """
    fixed = (posterior.inputs, posterior.beta, posterior.inv_k, posterior.log_ell, posterior.log_alpha)
    if fused and not any(t.requires_grad for t in fixed):  # the model is fixed (policy search, sampling): one fused pass
        return _PredictLatent.apply(test_inputs, posterior.inputs, posterior.beta, posterior.inv_k,
                                    posterior.log_ell, posterior.log_alpha)
    k = se_ard(posterior.inputs, test_inputs, posterior.log_ell, posterior.log_alpha)  # (E, n, m)
    mean = (posterior.beta[:, :, None] * k).sum(1)
    var = torch.exp(2.0 * posterior.log_alpha)[:, None] - (k * (posterior.inv_k @ k)).sum(1)
    return mean.T, var.T


class _PredictLatent(torch.autograd.Function):
    """:func:`predict_latent` for a fixed model, differentiable in the test inputs only, with the gradient
    in closed form instead of autograd's ~15 passes over ``(E, m, n)`` temporaries (``mc-pilco``'s particles
    spend most of an Adam step here). With ``k_a(x)_i = alpha_a^2 exp(-1/2 |(x - X_i) / ell_a|^2)`` and
    ``A_a`` = ``inv_k[a]`` (symmetric)::

        d mean_a / dx = sum_i beta_ai dk_i/dx,   d var_a / dx = -2 sum_i (A_a k_a)_i dk_i/dx,
        dk_i/dx = -k_i (x - X_i) / ell_a^2,

    so with ``w_ai = k_ai (g_mean_a beta_ai - 2 g_var_a (A_a k_a)_i)`` the gradient is
    ``sum_a ((w_a @ X) - (sum_i w_ai) x) / ell_a^2``: elementwise work and one ``(m, n) x (n, d)`` product per
    output. ``k`` and ``A k`` are kept from the forward pass (the one ``(m, n) x (n, n)`` product per output).
    ``k`` is :func:`~plugins.pilco.kernels.se_ard`'s; its squared distance is clamped at 0, and the gradient
    there (a test input on a basis point, to rounding) is taken as if unclamped."""

    @staticmethod
    def forward(ctx, x, inputs, beta, inv_k, log_ell, log_alpha):
        k = se_ard(x, inputs, log_ell, log_alpha)  # (E, m, n)
        mean = (k @ beta[:, :, None])[..., 0]  # (E, m)
        ka = k @ inv_k  # (E, m, n): (A k)^T, A symmetric
        var = torch.exp(2.0 * log_alpha)[:, None] - (ka * k).sum(-1)
        ctx.save_for_backward(x, inputs, beta, log_ell, k, ka)
        return mean.T, var.T

    @staticmethod
    def backward(ctx, g_mean, g_var):
        x, inputs, beta, log_ell, k, ka = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return (None,) * 6
        w = k * (g_mean.T[:, :, None] * beta[:, None, :] - 2.0 * g_var.T[:, :, None] * ka)  # (E, m, n)
        inv_ell = torch.exp(-log_ell)
        grad = ((w @ inputs - w.sum(-1)[:, :, None] * x) * (inv_ell * inv_ell)[:, None, :]).sum(0)  # (m, d)
        return grad, None, None, None, None, None


# ----------------------------------------------------------------------------- optimisation


@dataclass
class MinimiseResult:
    """Outcome of :func:`minimise_lbfgsb`: best ``x`` (flat), its objective value, evaluation and
    iteration counts (iterations -1 if stopped by a numerical failure), termination message."""

    x: torch.Tensor
    value: float
    evaluations: int
    iterations: int
    message: str


class _TrialPointFailed(Exception):
    """Internal: the objective failed at an L-BFGS-B trial point (not the start)."""


def minimise_lbfgsb(
    objective: Callable[[torch.Tensor], torch.Tensor],
    x0: torch.Tensor,
    lower: torch.Tensor | None,
    upper: torch.Tensor | None,
    max_evals: int,
) -> MinimiseResult:
    """Minimise a scalar torch function of a flat float64 vector with scipy's L-BFGS-B.

    Gradients come from autograd. Returns the best point evaluated. If the objective fails at a
    trial point (non-finite value or gradient, or a Cholesky :class:`NumericalError`) the
    optimisation stops there and the best point so far is returned (L-BFGS-B has no safe way to
    continue: ``inf`` makes it report convergence, a made-up value misleads its line search); at
    the starting point the :class:`NumericalError` propagates. ``max_evals`` bounds function
    evaluations (0: just evaluate at ``x0``). The objective is evaluated on ``x0``'s device; the
    optimiser's vectors stay on the host (one transfer each way per evaluation).
    """
    device = x0.device
    x0_np = x0.detach().cpu().numpy().astype(np.float64).copy()
    bounds = None
    if lower is not None and upper is not None:
        lo, hi = lower.detach().cpu().numpy(), upper.detach().cpu().numpy()
        x0_np = np.clip(x0_np, lo, hi)
        bounds = list(zip(lo.tolist(), hi.tolist()))
    count = [0]
    best: dict = {"x": x0_np.copy(), "f": math.inf}

    def fun(x_np: np.ndarray) -> tuple[float, np.ndarray]:
        count[0] += 1
        x = torch.tensor(x_np, dtype=DTYPE, device=device, requires_grad=True)
        try:
            value = objective(x)
            (grad,) = torch.autograd.grad(value, x)
        except NumericalError:
            if count[0] == 1:
                raise
            raise _TrialPointFailed() from None
        v = float(value.detach())
        if not math.isfinite(v) or not bool(torch.isfinite(grad).all()):
            if count[0] == 1:
                raise NumericalError("the GP training objective is not finite at the starting point")
            raise _TrialPointFailed()
        if v < best["f"]:
            best["x"], best["f"] = x_np.copy(), v
        return v, grad.cpu().numpy().copy()

    if max_evals <= 0:
        value, _ = fun(x0_np)
        return MinimiseResult(torch.tensor(x0_np, dtype=DTYPE, device=device), value, 1, 0, "no optimisation (budget 0)")
    # scipy's L-BFGS-B calls BLAS on tiny vectors; a multi-threaded OpenBLAS there cost ~3 ms per
    # iteration (more than a whole n = 100 GP evaluation) on a loaded 2-core machine.
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            res = scipy.optimize.minimize(
                fun,
                x0_np,
                jac=True,
                method="L-BFGS-B",
                bounds=bounds,
                options={"maxfun": max_evals, "maxiter": max_evals},
            )
        iterations, message = int(res.nit), str(res.message)
    except _TrialPointFailed:
        iterations = -1
        message = f"STOPPED: numerical failure at trial point {count[0]}; best point so far returned"
    return MinimiseResult(torch.tensor(best["x"], dtype=DTYPE, device=device), best["f"], count[0], iterations, message)


def _pack(h: GPHyperparameters) -> torch.Tensor:
    return torch.cat([h.log_ell.reshape(-1), h.log_alpha, h.log_sigma])


def _unpack(x: torch.Tensor, num_outputs: int, dim: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    k = num_outputs * dim
    return x[:k].reshape(num_outputs, dim), x[k : k + num_outputs], x[k + num_outputs :]


def penalised_nll(
    inputs: torch.Tensor, targets: torch.Tensor, hyp: GPHyperparameters, curb: bool = True
) -> torch.Tensor:
    """Training objective per output, ``(E,)``: NLL plus (if ``curb``) the hypCurb penalty."""
    nll = negative_log_marginal_likelihood(inputs, targets, hyp.log_ell, hyp.log_alpha, hyp.log_sigma)
    if curb:
        nll = nll + hyp_curb_penalty(hyp.log_ell, hyp.log_alpha, hyp.log_sigma, input_scale(inputs))
    return nll


def hyperparameter_bounds(
    inputs: torch.Tensor, targets: torch.Tensor, floor: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat L-BFGS-B box ``(lower, upper)`` in the packing order (log_ell, log_alpha, log_sigma).

    ``log sigma >= log floor`` is the noise floor; the other limits lie far outside the hypCurb box
    (penalty ~1e14 there) and only keep trial points finite.
    """
    num_outputs, dim = targets.shape[1], inputs.shape[1]
    log_s = torch.log(input_scale(inputs)).expand(num_outputs, dim)
    log_top = torch.log(torch.maximum(targets.pow(2).mean(0).sqrt(), target_scale(targets))) + CURB_LOG_SNR
    log_floor = torch.log(floor)
    lower = torch.cat([(log_s - _BOX_LOG_ELL).reshape(-1), log_floor - _BOX_LOG_AMPLITUDE, log_floor])
    upper = torch.cat([(log_s + _BOX_LOG_ELL).reshape(-1), log_top, torch.maximum(log_top, log_floor + 1.0)])
    return lower, upper


def optimise_hyperparameters(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    init: GPHyperparameters,
    floor: torch.Tensor,
    max_evals: int,
    curb: bool = True,
) -> tuple[GPHyperparameters, torch.Tensor, MinimiseResult]:
    """Evidence maximisation of all ``E`` GPs at once (objective: sum of penalised NLLs).

    Returns the hyperparameters, their penalised NLL per output ``(E,)`` and the optimiser record.
    """
    num_outputs, dim = targets.shape[1], inputs.shape[1]
    input_std = input_scale(inputs)

    def objective(x: torch.Tensor) -> torch.Tensor:
        log_ell, log_alpha, log_sigma = _unpack(x, num_outputs, dim)
        nll = negative_log_marginal_likelihood(inputs, targets, log_ell, log_alpha, log_sigma)
        if curb:
            nll = nll + hyp_curb_penalty(log_ell, log_alpha, log_sigma, input_std)
        return nll.sum()

    lower, upper = hyperparameter_bounds(inputs, targets, floor)
    result = minimise_lbfgsb(objective, _pack(init), lower, upper, max_evals)
    log_ell, log_alpha, log_sigma = _unpack(result.x, num_outputs, dim)
    hyp = GPHyperparameters(log_ell.clone(), log_alpha.clone(), log_sigma.clone())
    with torch.no_grad():
        per_output = penalised_nll(inputs, targets, hyp, curb)
    return hyp, per_output, result


def optimise_pseudo_inputs(
    inputs: torch.Tensor,
    targets: torch.Tensor,
    hyp: GPHyperparameters,
    init_pseudo_inputs: torch.Tensor,
    max_evals: int,
    ridge: float = FITC_RIDGE,
) -> tuple[torch.Tensor, torch.Tensor, MinimiseResult]:
    """Optimise the shared pseudo-inputs ``(M, d)`` on the summed FITC NLML, hyperparameters fixed.

    Returns the pseudo-inputs, the FITC NLML per output ``(E,)`` and the optimiser record.
    """
    shape = init_pseudo_inputs.shape
    log_ell, log_alpha, log_sigma = (t.detach() for t in (hyp.log_ell, hyp.log_alpha, hyp.log_sigma))

    def objective(x: torch.Tensor) -> torch.Tensor:
        z = x.reshape(shape)  # hand-derived gradient (sparse.fitc_nll_and_pseudo_gradient)
        return fitc_nll_of_pseudo_inputs(inputs, targets, z, log_ell, log_alpha, log_sigma, ridge).sum()

    result = minimise_lbfgsb(objective, init_pseudo_inputs.reshape(-1), None, None, max_evals)
    z = result.x.reshape(shape).clone()
    with torch.no_grad():
        per_output = fitc_negative_log_likelihood(inputs, targets, z, log_ell, log_alpha, log_sigma, ridge)
    return z, per_output, result


# ----------------------------------------------------------------------------- model


@dataclass
class FitReport:
    """What :meth:`GPModel.fit` did.

    Attributes:
        hyperparameters: the returned hyperparameters (with pseudo-inputs if sparse).
        nll: penalised full-GP NLL summed over outputs at the returned hyperparameters, on the
            points used for hyperparameter training (nats).
        nll_per_output: ``(E,)`` the same per output.
        restart_nlls: ``(restarts + 1, E)`` penalised NLL reached by every run (row 0: unperturbed).
        fitc_nll: FITC NLML summed over outputs on all points (sparse only), else ``None``.
        evaluations: objective+gradient evaluations, all runs and stages.
        iterations: L-BFGS-B iterations, all runs and stages.
        seconds: wall time of the fit.
        sparse: whether FITC took over.
        n_points: training points; n_hyper_points: points used for the hyperparameters.
        messages: L-BFGS-B termination messages, one per optimisation.
    """

    hyperparameters: GPHyperparameters
    nll: float
    nll_per_output: np.ndarray
    restart_nlls: np.ndarray
    fitc_nll: float | None
    evaluations: int
    iterations: int
    seconds: float
    sparse: bool
    n_points: int
    n_hyper_points: int
    messages: list[str] = field(default_factory=list)


def _as_data(inputs, targets, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.as_tensor(inputs, dtype=DTYPE, device=device).detach()
    y = torch.as_tensor(targets, dtype=DTYPE, device=device).detach()
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0] or x.shape[0] < 1:
        raise ValueError(f"expected inputs (n, d) and targets (n, E), got {tuple(x.shape)} and {tuple(y.shape)}")
    if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(y).all())):
        raise NumericalError("GP training data contain NaN or inf; check the recorded episodes")
    return x, y


class GPModel:
    """PILCO dynamics model: full GP up to ``sparse_threshold`` points, FITC above.

    Args:
        sparse_threshold: FITC takes over when ``n > sparse_threshold`` (and ``n > num_pseudo``).
        num_pseudo: ``M`` shared pseudo-inputs.
        max_evals_full: L-BFGS-B function-evaluation budget of each hyperparameter run (the
            reference allows 300 line searches; runs here converge in ~150-250 evaluations).
        max_evals_fitc: budget of a warm-started pseudo-input optimisation; the first one, from a
            random subset of the inputs, gets ``fitc_first_factor`` times more (the reference
            triples it). One FITC evaluation costs O(E n M^2): ~0.4 s for n = 1000, M = 300, E = 4
            on one core, hence the smaller budget than the reference's 500 line searches.
        fitc_first_factor: see above.
        hyper_subset: at most this many random points train the hyperparameters when sparse
            (default ``sparse_threshold``).
        pseudo_subset: when sparse, at most this many random points train the pseudo-inputs (default: all;
            at least ``num_pseudo``). One pseudo-input evaluation costs O(E n M^2), so a late double-pendulum
            fit (n ~ 1,200-2,400) spends most of its time there; the posterior is always computed from all points.
        refresh_pseudo: draw the pseudo-inputs afresh (a random subset of the current data,
            budget ``max_evals_fitc``) at every fit instead of continuing from a warm start's;
            on the double pendulum the carried-over ones model the newer data worse
            (``results/benchmarks/gp_budget_check_double-pendulum_62916e51_seeds0_warm.md``).
        noise_floor_rel, noise_floor_abs: ``sigma_a >= max(rel * scale(y_a), abs)``.
        curb: add the hypCurb penalty (switch off only for ablations/tests).
        restart_scale: std of the Gaussian perturbation of the log-hyperparameters per restart.
        fitc_ridge: jitter on K_mm relative to alpha^2.
        device: where training and the posterior live (data, hyperparameters and the returned
            posterior are on it; ``"cuda"`` for a GPU).
    """

    def __init__(
        self,
        sparse_threshold: int = 300,
        num_pseudo: int = 300,
        max_evals_full: int = 300,
        max_evals_fitc: int = 100,
        fitc_first_factor: int = 3,
        hyper_subset: int | None = None,
        pseudo_subset: int | None = None,
        refresh_pseudo: bool = False,
        noise_floor_rel: float = NOISE_FLOOR_REL,
        noise_floor_abs: float = NOISE_FLOOR_ABS,
        curb: bool = True,
        restart_scale: float = 1.0,
        fitc_ridge: float = FITC_RIDGE,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        if num_pseudo < 1 or sparse_threshold < 1 or max_evals_full < 0 or max_evals_fitc < 0:
            raise ValueError("GPModel needs num_pseudo, sparse_threshold >= 1 and budgets >= 0")
        self.sparse_threshold = int(sparse_threshold)
        self.num_pseudo = int(num_pseudo)
        self.max_evals_full = int(max_evals_full)
        self.max_evals_fitc = int(max_evals_fitc)
        self.fitc_first_factor = int(fitc_first_factor)
        self.hyper_subset = int(hyper_subset if hyper_subset is not None else sparse_threshold)
        if pseudo_subset is not None and int(pseudo_subset) < self.num_pseudo:
            raise ValueError(f"GPModel: pseudo_subset={pseudo_subset} is below num_pseudo={self.num_pseudo}; "
                             "the pseudo-inputs need at least as many points to train on (raise it, or leave it unset)")
        self.pseudo_subset = None if pseudo_subset is None else int(pseudo_subset)
        self.refresh_pseudo = bool(refresh_pseudo)
        self.noise_floor_rel = float(noise_floor_rel)
        self.noise_floor_abs = float(noise_floor_abs)
        self.curb = bool(curb)
        self.restart_scale = float(restart_scale)
        self.fitc_ridge = float(fitc_ridge)
        self._inputs: torch.Tensor | None = None
        self._targets: torch.Tensor | None = None
        self._hyp: GPHyperparameters | None = None
        self._posterior: GPPosterior | None = None

    # -- training -------------------------------------------------------------------------

    def uses_sparse(self, n: int) -> bool:
        """Whether ``n`` training points make the model sparse."""
        return n > self.sparse_threshold and n > self.num_pseudo

    def fit(
        self,
        inputs,
        targets,
        *,
        warm_start: GPHyperparameters | None = None,
        max_evals: int | None = None,
        restarts: int = 0,
        seed: int = 0,
    ) -> FitReport:
        """Train on ``inputs (n, d)``, ``targets (n, E)`` and return a :class:`FitReport`.

        Args:
            warm_start: previous hyperparameters to start from (instead of the reference
                initialisation); its pseudo-inputs are reused if they have shape ``(M, d)``.
            max_evals: overrides ``max_evals_full`` for this call.
            restarts: extra hyperparameter runs from the start perturbed by
                ``N(0, restart_scale^2)`` in log space; the best run per output is kept.
            seed: seeds the restarts and the random subsets (hyperparameter subset, first
                pseudo-inputs).
        """
        start = time.perf_counter()
        x, y = _as_data(inputs, targets, self.device)
        n, dim = x.shape
        num_outputs = y.shape[1]
        gen = torch.Generator().manual_seed(int(seed))  # draws on the host, then moved: same numbers on every device
        sparse = self.uses_sparse(n)
        budget = self.max_evals_full if max_evals is None else int(max_evals)

        if sparse and n > self.hyper_subset:
            idx = torch.randperm(n, generator=gen, device="cpu")[: self.hyper_subset].to(self.device)
            x_h, y_h = x[idx], y[idx]
        else:
            x_h, y_h = x, y
        floor = noise_floor(y_h, self.noise_floor_rel, self.noise_floor_abs)
        if warm_start is not None:
            if tuple(warm_start.log_ell.shape) != (num_outputs, dim):
                raise ValueError(
                    f"warm start has log_ell {tuple(warm_start.log_ell.shape)}, data need {(num_outputs, dim)}"
                )
            init = GPHyperparameters(*(torch.as_tensor(t, dtype=DTYPE, device=self.device).detach().clone() for t in (
                warm_start.log_ell, warm_start.log_alpha, warm_start.log_sigma)))
        else:
            init = initial_hyperparameters(x_h, y_h)

        runs: list[tuple[GPHyperparameters, torch.Tensor]] = []
        evaluations = iterations = 0
        messages: list[str] = []
        for r in range(int(restarts) + 1):
            start_hyp = init
            if r > 0:
                noise = self.restart_scale * torch.randn(_pack(init).shape, generator=gen, dtype=DTYPE, device="cpu").to(self.device)
                start_hyp = GPHyperparameters(*_unpack(_pack(init) + noise, num_outputs, dim))
            hyp, per_output, res = optimise_hyperparameters(x_h, y_h, start_hyp, floor, budget, self.curb)
            runs.append((hyp, per_output))
            evaluations += res.evaluations
            iterations += max(res.iterations, 0)
            messages.append(f"hyperparameters run {r}: {res.message}")
        restart_nlls = torch.stack([p for _, p in runs])  # (R+1, E)
        best = restart_nlls.argmin(0)  # (E,)
        rows = torch.arange(num_outputs, device=self.device)
        best_hyp = GPHyperparameters(
            log_ell=torch.stack([h.log_ell for h, _ in runs])[best, rows],
            log_alpha=torch.stack([h.log_alpha for h, _ in runs])[best, rows],
            log_sigma=torch.stack([h.log_sigma for h, _ in runs])[best, rows],
        )
        best_nll = restart_nlls[best, rows]

        fitc_nll = None
        if sparse:
            m = self.num_pseudo
            previous = None if warm_start is None else warm_start.pseudo_inputs
            warm = previous is not None and tuple(previous.shape) == (m, dim)
            if warm and not self.refresh_pseudo:
                z0 = torch.as_tensor(previous, dtype=DTYPE, device=self.device).detach().clone()
            else:
                z0 = x[torch.randperm(n, generator=gen, device="cpu")[:m].to(self.device)].clone()
            fitc_budget = self.max_evals_fitc * (1 if warm else self.fitc_first_factor)
            x_z, y_z = x, y
            if self.pseudo_subset is not None and n > self.pseudo_subset:  # drawn after z0: runs without it draw as before
                keep = torch.randperm(n, generator=gen, device="cpu")[: self.pseudo_subset].to(self.device)
                x_z, y_z = x[keep], y[keep]
            z, fitc_per_output, res = optimise_pseudo_inputs(x_z, y_z, best_hyp, z0, fitc_budget, self.fitc_ridge)
            if x_z.shape[0] < n:  # the reported FITC NLL is the model's, on all points
                with torch.no_grad():
                    fitc_per_output = fitc_negative_log_likelihood(
                        x, y, z, best_hyp.log_ell, best_hyp.log_alpha, best_hyp.log_sigma, self.fitc_ridge)
            best_hyp.pseudo_inputs = z
            fitc_nll = float(fitc_per_output.sum())
            evaluations += res.evaluations
            iterations += max(res.iterations, 0)
            messages.append(f"pseudo-inputs: {res.message}")

        self._inputs, self._targets, self._hyp = x, y, best_hyp
        self._posterior = self._compute_posterior()
        return FitReport(
            hyperparameters=best_hyp.clone(),
            nll=float(best_nll.sum()),
            nll_per_output=best_nll.cpu().numpy().copy(),
            restart_nlls=restart_nlls.cpu().numpy().copy(),
            fitc_nll=fitc_nll,
            evaluations=evaluations,
            iterations=iterations,
            seconds=time.perf_counter() - start,
            sparse=sparse,
            n_points=n,
            n_hyper_points=int(x_h.shape[0]),
            messages=messages,
        )

    # -- prediction -----------------------------------------------------------------------

    def _require_fitted(self) -> None:
        if self._hyp is None:
            raise RuntimeError("GPModel used before fit() or load_state_dict()")

    def _compute_posterior(self) -> GPPosterior:
        h = self._hyp
        with torch.no_grad():
            if h.pseudo_inputs is not None:
                return fitc_posterior(
                    self._inputs, self._targets, h.pseudo_inputs, h.log_ell, h.log_alpha, h.log_sigma, self.fitc_ridge
                )
            return full_posterior(self._inputs, self._targets, h.log_ell, h.log_alpha, h.log_sigma)

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """A copy of the current hyperparameters (pass as ``warm_start`` to the next fit)."""
        self._require_fitted()
        return self._hyp.clone()

    @property
    def sparse(self) -> bool:
        self._require_fitted()
        return self._hyp.pseudo_inputs is not None

    def posterior(self, max_basis: int | None = None) -> GPPosterior:
        """The trained model as a (detached) :class:`GPPosterior` for moment matching.

        ``max_basis``: plan with at most this many basis points. Where the model has more (FITC
        pseudo-inputs, or a full GP's training inputs), a FITC posterior on that many of them,
        chosen greedily where they explain the kernel at the data best, with the same hyperparameters and data
        (:func:`plugins.pilco.sparse.reduced_posterior`); ``None`` or a larger number: the model itself.
        """
        self._require_fitted()
        h = self._hyp
        basis = h.pseudo_inputs if h.pseudo_inputs is not None else self._inputs
        if max_basis is None or max_basis >= basis.shape[0]:
            return self._posterior
        if max_basis < 1:
            raise ValueError(f"max_basis={max_basis}: need at least 1 basis point")
        with torch.no_grad():
            return reduced_posterior(self._inputs, self._targets, basis, h.log_ell, h.log_alpha, h.log_sigma,
                                     max_basis, self.fitc_ridge)

    def predict(self, test_inputs, include_noise: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(m, E)`` and variance ``(m, E)`` at deterministic inputs ``(m, d)``.

        The variance is that of the latent function (as in moment matching); ``include_noise``
        adds ``sigma_a^2``.
        """
        self._require_fitted()
        xs = torch.as_tensor(test_inputs, dtype=DTYPE, device=self.device)
        with torch.no_grad():
            mean, var = predict_latent(self._posterior, xs)
            if include_noise:
                var = var + torch.exp(2.0 * self._hyp.log_sigma)[None, :]
        return mean, var

    # -- checkpoints ----------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Training data, hyperparameters and pseudo-inputs (tensors and a bool only)."""
        self._require_fitted()
        h = self._hyp
        z = h.pseudo_inputs if h.pseudo_inputs is not None else self._inputs.new_zeros(0, self._inputs.shape[1])
        return {  # on the host, whatever the model's device
            "inputs": self._inputs.cpu().clone(),
            "targets": self._targets.cpu().clone(),
            "log_ell": h.log_ell.cpu().clone(),
            "log_alpha": h.log_alpha.cpu().clone(),
            "log_sigma": h.log_sigma.cpu().clone(),
            "pseudo_inputs": z.cpu().clone(),
            "sparse": h.pseudo_inputs is not None,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a model saved with :meth:`state_dict` (the posterior is recomputed)."""
        x, y = _as_data(state["inputs"], state["targets"], self.device)
        z = torch.as_tensor(state["pseudo_inputs"], dtype=DTYPE, device=self.device) if bool(state["sparse"]) else None
        self._inputs, self._targets = x, y
        self._hyp = GPHyperparameters(
            torch.as_tensor(state["log_ell"], dtype=DTYPE, device=self.device).clone(),
            torch.as_tensor(state["log_alpha"], dtype=DTYPE, device=self.device).clone(),
            torch.as_tensor(state["log_sigma"], dtype=DTYPE, device=self.device).clone(),
            None if z is None else z.clone(),
        )
        self._posterior = self._compute_posterior()
