"""Random GP posteriors and a Monte Carlo reference for the moment-matching tests (test helper)."""

from __future__ import annotations

import torch

from plugins.pilco.kernels import se_ard
from plugins.pilco.posterior import GPPosterior

DT = torch.float64


def random_posterior(num_outputs: int, num_points: int, dim: int, gen: torch.Generator, fitc: bool = False) -> GPPosterior:
    """A full GP trained on random data (or a FITC-shaped posterior on random pseudo-inputs).

    Full: ``inv_k = (K + sigma^2 I)^-1``, ``beta = inv_k @ y`` with ``y`` a smooth random function.
    FITC-shaped: ``inv_k = Kmm^-1 - (Kmm + B)^-1`` with a random PSD ``B`` per output, so that
    ``inv_k`` is not the inverse of any Gram matrix; ``beta`` random.
    """
    X = torch.randn(num_points, dim, generator=gen, dtype=DT)
    log_ell = torch.log(0.6 + 1.2 * torch.rand(num_outputs, dim, generator=gen, dtype=DT))
    log_alpha = torch.log(0.5 + torch.rand(num_outputs, generator=gen, dtype=DT))
    log_sigma = torch.log(0.05 + 0.1 * torch.rand(num_outputs, generator=gen, dtype=DT))
    K = se_ard(X, X, log_ell, log_alpha)
    eye = torch.eye(num_points, dtype=DT)
    if fitc:
        Kmm = K + 1e-6 * eye
        G = torch.randn(num_outputs, num_points, num_points, generator=gen, dtype=DT) / num_points**0.5
        B = G @ G.mT * 3.0
        inv_k = torch.linalg.inv(Kmm) - torch.linalg.inv(Kmm + B)
        inv_k = 0.5 * (inv_k + inv_k.mT)
        beta = torch.randn(num_outputs, num_points, generator=gen, dtype=DT)
    else:
        w = torch.randn(num_outputs, dim, generator=gen, dtype=DT)
        y = torch.sin(X @ w.T).T + 0.1 * torch.randn(num_outputs, num_points, generator=gen, dtype=DT)
        return posterior_from_data(X, y.T, log_ell, log_alpha, log_sigma)
    return GPPosterior(X, beta, inv_k, log_ell, log_alpha, log_sigma)


def posterior_from_data(X, Y, log_ell, log_alpha, log_sigma) -> GPPosterior:
    """Full GP on data ``X (n, d)``, ``Y (n, E)`` with given hyperparameters (textbook formulas)."""
    K = se_ard(X, X, log_ell, log_alpha)
    inv_k = torch.linalg.inv(K + torch.exp(2 * log_sigma)[:, None, None] * torch.eye(X.shape[0], dtype=DT))
    inv_k = 0.5 * (inv_k + inv_k.mT)
    beta = (inv_k @ Y.T[..., None]).squeeze(-1)
    return GPPosterior(X, beta, inv_k, log_ell, log_alpha, log_sigma)


def random_gaussian(dim: int, gen: torch.Generator, scale: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """A random mean and a random full-rank covariance (std around ``scale``)."""
    m = 0.5 * torch.randn(dim, generator=gen, dtype=DT)
    A = torch.randn(dim, dim, generator=gen, dtype=DT) * scale / dim**0.5
    S = A @ A.T + 0.05 * scale**2 * torch.eye(dim, dtype=DT)
    return m, S


def gp_mean_var(posterior: GPPosterior, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic-input predictions at samples ``x (N, d)``: mean ``(N, E)``, latent variance ``(N, E)``."""
    k = se_ard(x, posterior.inputs, posterior.log_ell, posterior.log_alpha)  # (E, N, n)
    mean = torch.einsum("anm,am->na", k, posterior.beta)
    var = torch.exp(2 * posterior.log_alpha)[None, :] - torch.einsum("anm,amk,ank->na", k, posterior.inv_k, k)
    return mean, var


def mc_moments(samples_f: torch.Tensor, samples_x: torch.Tensor, extra_var: torch.Tensor | None = None):
    """MC estimates and standard errors of E[f], Cov[f] (+ diag(mean extra_var)), Cov[x, f].

    Returns ``(mean, mean_se, cov, cov_se, cross, cross_se)``.
    """
    n = samples_f.shape[0]
    fc = samples_f - samples_f.mean(0)
    xc = samples_x - samples_x.mean(0)
    mean = samples_f.mean(0)
    mean_se = samples_f.std(0) / n**0.5
    prod = fc[:, :, None] * fc[:, None, :]
    cov = prod.mean(0)
    cov_se = prod.std(0) / n**0.5
    if extra_var is not None:
        cov = cov + torch.diag(extra_var.mean(0))
        cov_se = cov_se + torch.diag(extra_var.std(0) / n**0.5)
    cprod = xc[:, :, None] * fc[:, None, :]
    return mean, mean_se, cov, cov_se, cprod.mean(0), cprod.std(0) / n**0.5


def pendulum_posterior(num_points: int, gen: torch.Generator) -> GPPosterior:
    """A GP of a damped, driven pendulum's one-step differences (state [thetadot, theta], dt 0.1).

    GP inputs ``[thetadot, sin(theta), cos(theta), u]`` (``StateLayout.with_trig(2, [1])`` plus one
    control), outputs ``Delta = [Delta thetadot, Delta theta]``; fixed sensible hyperparameters.
    """
    thd = 6.0 * torch.rand(num_points, generator=gen, dtype=DT) - 3.0
    th = 2 * torch.pi * torch.rand(num_points, generator=gen, dtype=DT) - torch.pi
    u = 4.0 * torch.rand(num_points, generator=gen, dtype=DT) - 2.0
    dt = 0.1
    acc = -9.81 * torch.sin(th) - 0.5 * thd + u
    Y = torch.stack([dt * acc, dt * thd + 0.5 * dt**2 * acc], dim=1)
    X = torch.stack([thd, torch.sin(th), torch.cos(th), u], dim=1)
    log_ell = torch.log(torch.tensor([[3.0, 1.0, 1.0, 3.0], [3.0, 1.5, 1.5, 4.0]], dtype=DT))
    log_alpha = torch.log(Y.std(0))
    log_sigma = torch.log(torch.tensor([0.01, 0.01], dtype=DT))
    return posterior_from_data(X, Y, log_ell, log_alpha, log_sigma)
