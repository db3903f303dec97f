"""benchmarks/cmaes.py finds the minimum of quadratics it was not told about (an ill-conditioned,
rotated ellipsoid: the covariance must adapt) and of a noisy one to the noise's resolution."""

from __future__ import annotations

import numpy as np

from benchmarks.cmaes import minimise


def test_cmaes_finds_the_minimum_of_a_rotated_ill_conditioned_ellipsoid():
    rng = np.random.default_rng(3)
    n = 8
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    H = Q @ np.diag(np.logspace(0, 4, n)) @ Q.T  # condition number 1e4
    x_star = rng.standard_normal(n)
    f = lambda x, g: float((x - x_star) @ H @ (x - x_star))  # noqa: E731
    result = minimise(f, np.zeros(n), 1.0, generations=400, seed=1)
    assert result.best_f < 1e-10
    assert np.linalg.norm(result.best_x - x_star) < 1e-4
    assert result.evaluations == 400 * (4 + int(3 * np.log(n)))


def test_cmaes_on_a_noisy_objective_gets_within_the_noise():
    x_star = np.array([1.0, -2.0, 0.5])

    def f(x, g):
        noise = np.random.default_rng(g).normal(0.0, 1e-3)  # common random numbers within a generation
        return float(np.sum((x - x_star) ** 2) + noise)

    result = minimise(f, np.zeros(3), 0.5, generations=150, seed=0)
    assert np.linalg.norm(result.best_x - x_star) < 0.1 and np.linalg.norm(result.mean - x_star) < 0.1
