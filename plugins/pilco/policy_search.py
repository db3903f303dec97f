"""Policy improvement: L-BFGS-B on J(theta) with exact gradients (paper Alg. 1, lines 4-9).

scipy's L-BFGS-B drives :class:`~plugins.pilco.objective.PolicyObjective`. A trial point where
the closed form breaks down (Cholesky failure, non-finite J) counts as ``+inf`` so the line search
backs off, as the reference ``minimize`` bisects NaN evaluations back; the best finite point seen
is returned, so an optimisation can never end worse than where it started.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import torch
from threadpoolctl import threadpool_limits

from harness.errors import NumericalError
from plugins.pilco.objective import PolicyObjective


@dataclass
class PolicySearchResult:
    """Outcome of :func:`optimise_policy`.

    Attributes:
        theta: best parameters found (also written into the controller).
        J_before, J_after: objective at the start and at ``theta``.
        evaluations: J + dJ evaluations; iterations: L-BFGS-B iterations (~ line searches).
        failed_evaluations: trial points where the closed form failed (counted as +inf).
        seconds: wall time; message: scipy's termination message.
    """

    theta: np.ndarray
    J_before: float
    J_after: float
    evaluations: int
    iterations: int
    failed_evaluations: int
    seconds: float
    message: str


def optimise_policy(objective: PolicyObjective, max_iterations: int = 150, max_evaluations: int = 300) -> PolicySearchResult:
    """Minimise J(theta) from the controller's current parameters; leaves the best in the controller."""
    start = time.perf_counter()
    theta0 = objective.get_flat()
    best = {"J": math.inf, "theta": theta0.copy()}
    counts = {"evaluations": 0, "failed": 0}

    def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
        counts["evaluations"] += 1
        try:
            value, grad = objective.value_and_grad(theta)
        except (NumericalError, torch.linalg.LinAlgError):  # e.g. a propagated covariance lost definiteness
            value, grad = math.inf, np.zeros_like(theta)
        if not (math.isfinite(value) and np.all(np.isfinite(grad))):
            counts["failed"] += 1
            return math.inf, np.zeros_like(theta)
        if value < best["J"]:
            best["J"], best["theta"] = value, theta.copy()
        return value, grad

    J0, _ = fun(theta0)
    if not math.isfinite(J0):
        objective.set_flat(theta0)
        raise NumericalError("J(theta) is not finite at the starting policy; the dynamics model is degenerate")
    with threadpool_limits(limits=1, user_api="blas"):
        res = scipy.optimize.minimize(
            fun,
            theta0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": int(max_iterations), "maxfun": int(max_evaluations)},
        )
    objective.set_flat(best["theta"])
    return PolicySearchResult(
        theta=best["theta"],
        J_before=J0,
        J_after=best["J"],
        evaluations=counts["evaluations"],
        iterations=int(res.nit),
        failed_evaluations=counts["failed"],
        seconds=time.perf_counter() - start,
        message=str(res.message),
    )
