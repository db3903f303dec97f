"""Policy improvement: L-BFGS-B on J(theta) with exact gradients (paper Alg. 1, lines 4-9).

scipy's L-BFGS-B drives :class:`~plugins.pilco.objective.PolicyObjective`. A trial point where
the closed form breaks down (Cholesky failure, non-finite J) counts as ``+inf``. scipy's line
search does not bisect such points back as the reference ``minimize`` does (it stops abnormally),
so the search then restarts from the best point with a shorter first step (see
:func:`optimise_policy`). The best finite point seen is returned, so an optimisation can never end
worse than where it started. The initial J evaluation is not counted in ``max_evaluations``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
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
        seconds: wall time; message: scipy's termination message (of the last round).
        restarts: rounds restarted after a line search broke down on failed points.
        status: why it stopped, scipy's L-BFGS-B status of the last round: 0 converged (J or its
            gradient stopped changing), 1 a budget ran out (iterations or evaluations), 2 the line
            search stopped abnormally; -1 before any round ran.
    """

    theta: np.ndarray
    J_before: float
    J_after: float
    evaluations: int
    iterations: int
    failed_evaluations: int
    seconds: float
    message: str
    restarts: int = 0
    status: int = -1


#: scipy's L-BFGS-B makes its first step of unit length; after a line search that broke down on
#: failed points the search restarts from the best point with the parameters scaled so that the
#: first step is this factor shorter (at most MAX_RESTARTS restarts; the budgets bound them too)
RESTART_SHRINK = 0.1
MAX_RESTARTS = 20


def optimise_policy(objective: PolicyObjective, max_iterations: int = 150, max_evaluations: int = 300,
                    memory: int = 10, on_evaluation: Callable[[int, float], None] | None = None) -> PolicySearchResult:
    """Minimise J(theta) from the controller's current parameters; leaves the best in the controller.

    ``on_evaluation(evaluations, best J)``, if given, is called after every J + dJ (for progress; the
    initial evaluation is number 0, as the budget counts them).

    L-BFGS-B over ``z = theta / scale``. scipy's first step has unit length in ``z``; where that
    step lands on points whose closed form fails (+inf; e.g. a unicycle policy so strong that the
    propagated covariance degenerates) its line search stops. Then the search restarts
    from the best point with ``scale`` shrunk by :data:`RESTART_SHRINK` (unless the round improved
    J, which keeps the scale), sharing the iteration and evaluation budgets; a search without
    failures is exactly one scipy run.
    """
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
            value, grad = math.inf, np.zeros_like(theta)
        elif value < best["J"]:
            best["J"], best["theta"] = value, theta.copy()
        if on_evaluation is not None:
            on_evaluation(counts["evaluations"] - 1, best["J"])
        return value, grad

    J0, _ = fun(theta0)
    if not math.isfinite(J0):
        objective.set_flat(theta0)
        raise NumericalError("J(theta) is not finite at the starting policy; the dynamics model is degenerate")
    scale, iterations, restarts, message, status = 1.0, 0, 0, "", -1
    with threadpool_limits(limits=1, user_api="blas"):
        while True:
            failed_before, J_before_round = counts["failed"], best["J"]
            res = scipy.optimize.minimize(
                lambda z, s=scale: _scaled(fun, z, s),
                best["theta"] / scale,
                jac=True,
                method="L-BFGS-B",
                options={"maxiter": int(max_iterations) - iterations, "maxfun": int(max_evaluations) - (counts["evaluations"] - 1),
                         "maxcor": int(memory)},
            )
            iterations += int(res.nit)
            message, status = str(res.message), int(res.status)
            # stopped for another reason than the budget after meeting failed points: scipy's
            # line search does not back off from +inf (it reports an abnormal stop, or even
            # "convergence" with the zero gradient we return there)
            broke_down = res.status != 1 and counts["failed"] > failed_before
            budget_left = iterations < max_iterations and counts["evaluations"] < max_evaluations
            if not (broke_down and budget_left and restarts < MAX_RESTARTS):
                break
            restarts += 1
            if not best["J"] < J_before_round:
                scale *= RESTART_SHRINK
    objective.set_flat(best["theta"])
    return PolicySearchResult(
        theta=best["theta"],
        J_before=J0,
        J_after=best["J"],
        evaluations=counts["evaluations"],
        iterations=iterations,
        failed_evaluations=counts["failed"],
        seconds=time.perf_counter() - start,
        message=message,
        restarts=restarts,
        status=status,
    )


def _scaled(fun, z: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """``fun`` in the coordinates ``z = theta / scale``: ``(J, scale * dJ/dtheta)``."""
    value, grad = fun(z * scale)
    return value, grad * scale
