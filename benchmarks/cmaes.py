"""A small CMA-ES (Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772), minimising.

Weighted recombination of the best half, cumulative step-size adaptation and rank-one plus rank-mu
covariance updates with the tutorial's default constants; written from its equations for the
benchmarks that search policies on a true simulator (no dependency). :func:`minimise` is tested on
quadratics in ``tests/benchmarks/test_cmaes.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class CmaesResult:
    best_x: np.ndarray
    best_f: float
    generations: int
    evaluations: int
    #: the search distribution's mean at the end (for a noisy objective a better estimate than ``best_x``)
    mean: np.ndarray | None = None
    #: (generation, best f of the generation, mean f of the generation, sigma) per generation
    trace: list[tuple[int, float, float, float]] = field(default_factory=list)


def minimise(f: Callable[[np.ndarray, int], float], x0: np.ndarray, sigma0: float, generations: int,
             popsize: int | None = None, seed: int = 0, callback: Callable[[int, CmaesResult], None] | None = None) -> CmaesResult:
    """Minimise ``f(x, generation)`` from ``x0 (n,)`` with step size ``sigma0`` for ``generations``
    generations of ``popsize`` candidates (default ``4 + floor(3 ln n)``). ``f`` gets the generation
    so that a noisy objective can use common random numbers within one."""
    x0 = np.asarray(x0, dtype=np.float64)
    n = x0.size
    lam = popsize or 4 + int(3 * math.log(n))
    mu = lam // 2
    w = math.log((lam + 1) / 2) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mueff = 1.0 / np.sum(w**2)
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chin = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))

    rng = np.random.default_rng(seed)
    mean, sigma = x0.copy(), float(sigma0)
    C, pc, ps = np.eye(n), np.zeros(n), np.zeros(n)
    B, D = np.eye(n), np.ones(n)
    result = CmaesResult(x0.copy(), math.inf, 0, 0)
    for g in range(generations):
        z = rng.standard_normal((lam, n))
        y = (z * D) @ B.T  # ~ N(0, C)
        xs = mean + sigma * y
        fs = np.array([f(x, g) for x in xs])
        result.evaluations += lam
        order = np.argsort(fs)
        if fs[order[0]] < result.best_f:
            result.best_f, result.best_x = float(fs[order[0]]), xs[order[0]].copy()
        y_sel = y[order[:mu]]
        y_w = w @ y_sel
        mean = mean + sigma * y_w
        # C^(-1/2) y_w = B diag(1/D) B^T y_w
        ps = (1 - cs) * ps + math.sqrt(cs * (2 - cs) * mueff) * (B @ ((B.T @ y_w) / D))
        hsig = np.linalg.norm(ps) / math.sqrt(1 - (1 - cs) ** (2 * (g + 1))) / chin < 1.4 + 2 / (n + 1)
        pc = (1 - cc) * pc + hsig * math.sqrt(cc * (2 - cc) * mueff) * y_w
        rank_mu = (y_sel.T * w) @ y_sel
        C = (1 - c1 - cmu) * C + c1 * (np.outer(pc, pc) + (1 - hsig) * cc * (2 - cc) * C) + cmu * rank_mu
        sigma *= math.exp((cs / damps) * (np.linalg.norm(ps) / chin - 1))
        C = (C + C.T) / 2
        eigval, B = np.linalg.eigh(C)
        D = np.sqrt(np.clip(eigval, 1e-20, None))
        result.generations = g + 1
        result.mean = mean.copy()
        result.trace.append((g, float(fs[order[0]]), float(fs.mean()), sigma))
        if callback is not None:
            callback(g, result)
    return result
