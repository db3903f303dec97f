"""Policy search: L-BFGS-B backs off from points where the closed form breaks down."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from harness.errors import NumericalError
from plugins.pilco.policy_search import optimise_policy


class Quadratic:
    """``J = |theta - target|^2`` (the duck type of PolicyObjective); raises like a broken
    propagation (``torch.linalg.LinAlgError``) where ``theta[0] > wall``."""

    def __init__(self, target, wall=math.inf, error=torch.linalg.LinAlgError):
        self.theta = np.zeros(len(target))
        self.target, self.wall, self.error = np.asarray(target, dtype=float), wall, error
        self.calls = 0

    def get_flat(self):
        return self.theta.copy()

    def set_flat(self, theta):
        self.theta = np.asarray(theta, dtype=float).copy()

    def value_and_grad(self, theta):
        self.calls += 1
        self.set_flat(theta)
        if theta[0] > self.wall:
            raise self.error("linalg.cholesky: the input is not positive-definite")
        d = theta - self.target
        return float(d @ d), 2 * d


def test_converges_on_a_smooth_objective():
    objective = Quadratic([1.0, -2.0, 0.5])
    result = optimise_policy(objective, max_iterations=50, max_evaluations=100)
    np.testing.assert_allclose(result.theta, [1.0, -2.0, 0.5], atol=1e-6)
    assert result.J_before == pytest.approx(5.25) and result.J_after < 1e-10 and result.failed_evaluations == 0
    np.testing.assert_array_equal(objective.get_flat(), result.theta)  # the best is left in the controller
    assert result.status == 0 and "CONVERGENCE" in result.message


class Rosenbrock(Quadratic):
    """Rosenbrock's valley from (-1.2, 1): L-BFGS-B needs some 40 iterations to its minimum (1, 1)."""

    def __init__(self):
        super().__init__([1.0, 1.0])
        self.theta = np.array([-1.2, 1.0])

    def value_and_grad(self, theta):
        x, y = theta
        return float((1 - x) ** 2 + 100 * (y - x * x) ** 2), np.array([-2 * (1 - x) - 400 * x * (y - x * x), 200 * (y - x * x)])


@pytest.mark.parametrize("budget", [{"max_iterations": 5, "max_evaluations": 100}, {"max_iterations": 100, "max_evaluations": 8}])
def test_a_search_stopped_by_its_budget_says_so(budget):
    """``status`` 1 (and scipy's message) when the iterations or the evaluations ran out, 0 when it
    converged with budget to spare; logged per trial as ``policy_search_status``, so that a short
    search can be told from a converged one."""
    assert optimise_policy(Rosenbrock(), max_iterations=200, max_evaluations=400).status == 0
    result = optimise_policy(Rosenbrock(), **budget)
    assert result.status == 1 and "LIMIT" in result.message


@pytest.mark.parametrize("error", [torch.linalg.LinAlgError, NumericalError])
def test_failed_points_count_as_inf_and_the_best_finite_point_is_kept(error):
    objective = Quadratic([2.0, 1.0], wall=1.5, error=error)  # the minimum lies beyond the wall
    result = optimise_policy(objective, max_iterations=50, max_evaluations=100)
    assert result.failed_evaluations >= 1
    assert result.theta[0] <= 1.5 and math.isfinite(result.J_after) and result.J_after < result.J_before
    assert result.J_after == pytest.approx(float(np.sum((result.theta - [2.0, 1.0]) ** 2)))
    np.testing.assert_array_equal(objective.get_flat(), result.theta)


def test_a_broken_start_is_a_numerical_error_and_keeps_the_policy():
    objective = Quadratic([2.0], wall=-1.0)
    objective.set_flat(np.array([0.5]))
    with pytest.raises(NumericalError, match="not finite at the starting policy"):
        optimise_policy(objective)
    np.testing.assert_array_equal(objective.get_flat(), [0.5])


class TrustRegion(Quadratic):
    """Fails (like a degenerate propagation) farther than ``radius`` from the start."""

    def __init__(self, target, radius):
        super().__init__(target)
        self.radius = radius

    def value_and_grad(self, theta):
        if np.linalg.norm(theta) > self.radius:
            self.calls += 1
            raise torch.linalg.LinAlgError("linalg.cholesky: not positive-definite")
        return super().value_and_grad(theta)


def test_a_line_search_broken_by_failed_points_restarts_with_a_shorter_first_step():
    """scipy's first step has unit length and lands beyond the region where J exists; its line
    search then stops abnormally. The restart shrinks the step and makes progress to the boundary."""
    objective = TrustRegion([3.0, 4.0], radius=0.5)  # the target is at distance 5, unreachable
    result = optimise_policy(objective, max_iterations=100, max_evaluations=200)
    assert result.restarts >= 1 and result.failed_evaluations >= 1
    # the best point lies (nearly) at the boundary towards the target: J = (5 - 0.5)^2 = 20.25 at best
    assert result.J_after < 21.0 and result.J_before == pytest.approx(25.0)
    np.testing.assert_allclose(result.theta / np.linalg.norm(result.theta), [0.6, 0.8], atol=0.02)


def test_without_failures_it_is_exactly_one_scipy_run():
    import scipy.optimize

    target = np.array([1.0, -2.0, 0.5, 3.0])
    objective = Quadratic(target)
    result = optimise_policy(objective, max_iterations=3, max_evaluations=100)
    reference = scipy.optimize.minimize(lambda t: Quadratic(target).value_and_grad(t), np.zeros(4), jac=True, method="L-BFGS-B",
                                        options={"maxiter": 3, "maxfun": 100})
    assert result.restarts == 0 and result.iterations == reference.nit
    assert result.evaluations == reference.nfev + 1  # + the initial J evaluation
    np.testing.assert_array_equal(result.theta, reference.x)
