"""Linear control of the unicycle: its linearisation and a riding LQR (a reference controller).

Upright and at rest, neither torque enters the roll acceleration to first order (the turntable
yaws the unicycle, the wheel pitches it), so the falling roll mode cannot be moved by any linear
feedback about rest. Riding forward couples yaw rate into roll (speed x yaw rate), and a linear
policy can then balance. :func:`riding_lqr` gives the discrete LQR about riding straight at a
given speed: a yardstick for what a linear policy (PILCO's controller for this task) can reach
(``benchmarks/unicycle_linear_ceiling.py``, ``tests/tasks/test_unicycle.py``).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from tasks.unicycle import Unicycle

#: LQR weights on the 10 observation entries ``[thetadot, phidot, psidot_w, psidot_f, psidot_t,
#: x_c, y_c, theta, phi, psi_f]`` (``x_c`` gets none: riding straight, it drifts) and on the
#: torques ``[u_t, u_w]`` (Nm).
STATE_WEIGHTS = (1.0, 0.1, 0.1, 1.0, 0.001, 0.0, 0.01, 10.0, 0.01, 10.0)
TORQUE_WEIGHTS = (0.01, 0.0004)
#: observation index of ``x_c``, left out of the Riccati equation (uncontrollable drift while riding)
X_C = 5


def linearised_step(task: Unicycle, x0: np.ndarray, eps: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """``(A (10, 10), B (10, 2))`` of one noise-free env step at state ``x0`` (observation
    coordinates) with zero torques, by central differences of the true step."""
    env = task.make_env(measurement_noise=False)

    def step(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        env.reset(options={"state": x})
        return env.step(u)[4]["state"]

    A, B = np.zeros((10, 10)), np.zeros((10, 2))
    for i in range(10):
        e = np.eye(10)[i] * eps
        A[:, i] = (step(x0 + e, np.zeros(2)) - step(x0 - e, np.zeros(2))) / (2 * eps)
    for j in range(2):
        e = np.eye(2)[j] * eps
        B[:, j] = (step(x0, e) - step(x0, -e)) / (2 * eps)
    return A, B


def roll_mode_controllability(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """The unstable roll eigenvalue (the real one in (1.2, 2)) and the smallest singular value of
    ``[A - lambda I, B]`` there (PBH test: 0 = no linear feedback can move that mode)."""
    eig = np.linalg.eigvals(A)
    (lam,) = [v.real for v in eig if abs(v.imag) < 1e-9 and 1.2 < v.real < 2.0]
    sv = np.linalg.svd(np.hstack([A - lam * np.eye(10), B]), compute_uv=False)[-1]
    return lam, sv


def riding_lqr(task: Unicycle, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete LQR about riding straight at ``speed`` m/s: gain ``K (2, 10)`` and set point
    ``x* (10,)``; the control law is ``u = -K (x - x*)`` (before any bounds)."""
    x_star = np.zeros(10)
    x_star[2] = speed / task.params.r_w  # wheel rate of rolling at `speed`
    A, B = linearised_step(task, x_star)
    keep = [i for i in range(10) if i != X_C]
    Ar, Br = A[np.ix_(keep, keep)], B[keep]
    R = np.diag(TORQUE_WEIGHTS)
    P = scipy.linalg.solve_discrete_are(Ar, Br, np.diag(np.asarray(STATE_WEIGHTS)[keep]), R)
    K = np.zeros((2, 10))
    K[:, keep] = np.linalg.solve(R + Br.T @ P @ Br, Br.T @ P @ Ar)
    return K, x_star
