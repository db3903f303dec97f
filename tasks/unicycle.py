"""Robotic unicycle balancing, as in the PILCO reference implementation (``scenarios/unicycle``).

Physical state (12 coupled first-order ODEs, "based on derivations by David Forster")::

    z = [thetadot, phidot, psidot_w, psidot_f, psidot_t, x, y, theta, phi, psi_w, psi_f, psi_t]

theta = roll (sideways tilt), phi = yaw (heading), psi_w = wheel rotation, psi_f = frame pitch,
psi_t = turntable (flywheel) rotation, (x, y) = wheel contact point on the floor (m). Rates in
rad/s, angles in rad. Controls ``u = [u_t, u_w]``: torque on the turntable (|u_t| <= 10 Nm) and
on the wheel (|u_w| <= 50 Nm), the reference's ``maxU = [10 50]`` for ``[ct, cw]``.

Equations of motion (:func:`unicycle_system`, :func:`unicycle_matrices`, :func:`unicycle_rhs`; the
environment steps them with the fused RK4 of :func:`unicycle_stepper`): the five angular
accelerations are ``-A^{-1} b`` with the 5x5 ``A`` and ``b`` of the reference note §1.10.3; the
contact point rolls without slipping, ``xdot = r_w cos(phi) psidot_w``, ``ydot = r_w sin(phi)
psidot_w``; the angle derivatives are the rates. Friction torque ``T = 0`` as in the reference.
``A`` is singular only at ``|theta| = pi/2`` (roll/yaw Euler-angle singularity, on the fall
boundary); its condition number grows like ``1 / cos(theta)`` (about 250 upright).

Note on the reference's equations (kept as they are): the frame's inertia about the wheel axle
enters the pitch rows (A22, A24, A52, A54, and ``(C_w + A_t) phidot cos(theta) thetadot`` in b2, b5)
as the *wheel's* ``C_w = 0.0484``, but the frame's gyroscopic terms (E1, E2) as ``C_f = 0.8292``.
So the reference model does not conserve energy; with ``C_f = C_w`` it is a consistent rigid-body
model whose energy (:func:`total_energy`) is conserved to integration accuracy
(``tests/tasks/test_unicycle.py``), which checks every other term of the transcription.

Geometry used for the energy, the success test and the drawing (:func:`body_points`; the
conventions of the reference's ``draw_unicycle.m``, and those under which the equations conserve
energy when ``C_f = C_w``). With heading ``h = (cos phi, sin phi, 0)``, roll axis
``f = -h``, ``l = f x e_z`` and the wheel's in-plane "up" ``n = cos(theta) e_z + sin(theta) l``:
wheel centre ``W = P + r_w n`` above the contact point ``P``; the frame points along
``-sin(psi_f) f + cos(psi_f) n``, its centre of mass ``r_f`` and the turntable ``r = r_f + r_t``
from ``W``. So the top (turntable centre) sits at height ``(r_w + r cos psi_f) cos theta`` and at
the horizontal offset ``(r_w + r cos psi_f) sin theta`` sideways, ``r sin psi_f`` along the
heading, from the contact point.

Observation (what learners see): the reference's 10 planning states ``dyno``::

    x = [thetadot, phidot, psidot_w, psidot_f, psidot_t, x_c, y_c, theta, phi, psi_f]

with ``[x_c, y_c] = -R(phi) [x, y]``, ``R(phi) = [[cos, sin], [-sin, cos]]``: the lab origin in
the unicycle's frame. The dynamics do not depend on ``x, y, psi_w, psi_t`` (cyclic coordinates),
so the observation is a complete state for control; ``TaskSpec.physical_state_dim = 12``.
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import gymnasium as gym
import numpy as np

from harness.options import Option
from harness.task import Episode, SaturatingCost, Task, TaskSpec
from tasks.drawing import Canvas
from tasks.simulation import OdeEnv, RightHandSide, Stepper

#: observation entries (the reference's ``dyno``), with units.
STATE_NAMES = (
    "thetadot [rad/s]", "phidot [rad/s]", "psidot_w [rad/s]", "psidot_f [rad/s]", "psidot_t [rad/s]",
    "x_c [m]", "y_c [m]", "theta [rad]", "phi [rad]", "psi_f [rad]",
)
#: physical (ODE) state entries, with units.
PHYSICAL_STATE_NAMES = (
    "thetadot [rad/s]", "phidot [rad/s]", "psidot_w [rad/s]", "psidot_f [rad/s]", "psidot_t [rad/s]",
    "x [m]", "y [m]", "theta [rad]", "phi [rad]", "psi_w [rad]", "psi_f [rad]", "psi_t [rad]",
)
ACTION_NAMES = ("u_t turntable torque [Nm]", "u_w wheel torque [Nm]")
#: indices of the observation entries that the reference also has in the ODE state (identity part).
OBS_FROM_ODE = (0, 1, 2, 3, 4, 7, 8, 10)  # ODE indices of obs entries 0-4, 7, 8, 9
OBS_IDENTITY = (0, 1, 2, 3, 4, 7, 8, 9)  # the matching observation indices

#: Default RK4 sub-steps per second of system time: 30 per 0.15 s control step (option
#: ``substeps``; 4 right-hand-side evaluations per sub-step: ~25,000 env steps per CPU second with
#: the numba-compiled stepper, ~2,000 in plain Python, ``results/benchmarks/env_steps.md``). One-step max-abs error against :func:`tasks.simulation.reference_step`: 2.8e-6
#: (worst of 10 states with rates up to 2 rad/s, angles up to 0.6 rad, torques at the bounds;
#: ``test_rk4_step_matches_reference_solver`` checks < 1e-5); with 24 sub-steps 6.3e-6 at ~2,500
#: steps/s, with 20 1.2e-5. A fixed-step 8th-order Dormand-Prince does not need fewer evaluations
#: here (8e-5 with 4 steps = 48 evaluations). States already falling (angles ~1.2 rad, rates
#: ~3 rad/s) reach errors of order 1: near the fall boundary ``|theta| = pi/2`` the equations
#: become stiff (``A`` nearly singular).
SUBSTEPS_PER_SECOND = 200
#: seed and size of the Monte-Carlo estimate of the initial distribution in observation coordinates.
INIT_MC_SEED = 20110628
INIT_MC_SAMPLES = 100_000


@dataclass(frozen=True)
class UnicycleParams:
    """Physical parameters, SI units (``dynamics_unicycle.m``; reference note §1.10.1)."""

    m_t: float = 10.0  # turntable mass, kg
    m_w: float = 1.0  # wheel mass, kg
    m_f: float = 23.5  # frame mass, kg
    r_w: float = 0.225  # wheel radius, m
    r_f: float = 0.54  # frame centre of mass to wheel axle, m
    r_t: float = 0.27  # frame centre of mass to turntable, m
    C_w: float = 0.0484  # wheel inertia about its axle, kg m^2
    A_w: float = 0.0242  # wheel inertia perpendicular to the axle
    C_f: float = 0.8292  # frame inertia about the wheel axle
    B_f: float = 0.4608  # frame inertia about the third body axis
    A_f: float = 0.4248  # frame inertia about its long axis (axle to turntable)
    C_t: float = 0.2  # turntable inertia about its axle (the frame's long axis)
    A_t: float = 1.3  # turntable inertia perpendicular to its axle
    g: float = 9.82  # gravity, m/s^2
    T: float = 0.0  # friction torque ("no friction")

    @property
    def r(self) -> float:
        """Wheel axle to turntable, ``r_f + r_t`` (m)."""
        return self.r_f + self.r_t


#: ``system(thd, phd, pwd, pfd, ptd, theta, psi_f, u_t, u_w) -> (A entries..., b...)``, see :func:`unicycle_system`.
UnicycleSystem = Callable[..., tuple[float, ...]]


@lru_cache(maxsize=None)
def unicycle_system(p: UnicycleParams) -> UnicycleSystem:
    """The equations of motion as a closure over the parameters: the nonzero entries of ``A`` and ``b``.

    ``system(thd, phd, pwd, pfd, ptd, th, pf, V, U)`` takes the five rates (rad/s), the roll
    ``theta`` and the pitch ``psi_f`` (rad), the turntable and wheel torques ``V = u_t``, ``U = u_w``
    (Nm) and returns the 20 floats ``(A00, A01, A04, A11, A12, A13, A20, A21, A24, A30, A31, A34,
    A41, A42, A43, b0, b1, b2, b3, b4)`` (0-based; every other entry of the 5x5 ``A`` is zero) with
    ``[thdd, phdd, psdd_w, psdd_f, psdd_t] = -A^{-1} b`` (reference note §1.10.3). The right-hand
    side calls it 120 times per control step: the parameters are closure locals, not attributes.
    """
    m_t, m_w, m_f, r_w, r_f, r_t = p.m_t, p.m_w, p.m_f, p.r_w, p.r_f, p.r_t
    C_w, A_w, C_f, B_f, A_f, C_t, A_t, g, T = p.C_w, p.A_w, p.C_f, p.B_f, p.A_f, p.C_t, p.A_t, p.g, p.T
    r = r_f + r_t
    # constant sub-expressions of the equations below, evaluated once (the same floating-point
    # operations as inline: the results are bit-identical to the unhoisted transcription)
    AfCt, BfAt, CwAt, C2wAt, AfBfAt = A_f + C_t, B_f + A_t, C_w + A_t, 2 * C_w + A_t, A_f - B_f - A_t
    n_AfCt, n_BfAt, CfBf, CfAf = -(A_f + C_t), -(B_f + A_t), C_f - B_f, C_f - A_f
    mfg, mtg, M_g, Mft, Mft_g = m_f * g, m_t * g, (m_t + m_w + m_f) * g, m_f + m_t, (m_f + m_t) * g
    rtmt, mwrw, m2wrw, A2w = r_t * m_t, m_w * r_w, 2 * m_w * r_w, 2 * A_w
    mr_ft, mr_tf = m_f * r_f + m_t * r, m_t * r + m_f * r_f
    lever_m, rw2_M = r_f * (m_f + m_t) + r_t * m_t, r_w * r_w * (m_w + m_f + m_t)
    K = B_f + A_t + r_f * (m_f * r_f + m_t * r) + r_t * m_t * r
    A13 = -C_w - A_t - r_f * (m_f * r_f + m_t * r) - r_t * m_t * r
    n_Ct, n_Aw, n_rw, n_T = -C_t, -A_w, -r_w, -T
    sin, cos = math.sin, math.cos

    def system(
        thd: float, phd: float, pwd: float, pfd: float, ptd: float, th: float, pf: float, V: float, U: float
    ) -> tuple[float, ...]:
        st, ct, sf, cf = sin(th), cos(th), sin(pf), cos(pf)

        w1 = phd * sf * ct + cf * thd
        w2 = -phd * cf * ct + sf * thd
        w3 = -phd * st + pfd
        ww = -phd * st + pwd
        wt = -w2 + ptd
        a1 = phd * sf * pfd * ct + phd * cf * st * thd + cf * pfd * thd
        a2 = phd * cf * pfd * ct - phd * sf * st * thd - pfd * sf * thd

        # P, Q, R of the reference note are affine in the lever rho: X(rho) = X0 + rho X1
        wwr = ww * r_w
        P0 = sf * pfd * wwr + cf * phd * ct * thd * r_w - w3 * sf * wwr - w2 * thd * r_w
        P1 = phd * ct * thd - w2 * w1
        Q0 = w1 * sf * wwr - w2 * cf * wwr
        Q1 = a2 - w2 * w3
        R0 = -cf * pfd * wwr + sf * phd * ct * thd * r_w + w1 * thd * r_w + w3 * cf * wwr
        R1 = w1 * w1 + w3 * w3
        P_f, P_r, Q_f, Q_r, R_f, R_r = P0 + r_f * P1, P0 + r * P1, Q0 + r_f * Q1, Q0 + r * Q1, R0 + r_f * R1, R0 + r * R1
        E1 = n_AfCt * a1 - CfBf * w1 * w3
        E2 = n_BfAt * a2 + CfAf * w2 * w3 + A_t * w2 * w3 + C_t * w3 * wt
        G = r_f * (mfg * st - m_f * Q_f + mtg * st - m_t * Q_r) + r_t * (mtg * st - m_t * Q_r)
        H = (r_f * (mfg * sf * ct + m_f * P_f + mtg * sf * ct + m_t * P_r)
             + r_t * (mtg * sf * ct + m_t * P_r))
        L = r_f * (m_f * (cf * r_f + r_w) + m_t * (cf * r + r_w)) + rtmt * (cf * r + r_w)

        A00 = n_Ct * sf
        A01 = C_t * cf * ct
        A04 = C_t
        A11 = (CwAt * st + r_f * st * (m_f * (r_f + cf * r_w) + m_t * (r + cf * r_w))
               + rtmt * st * (r + cf * r_w))
        A12 = -cf * r_w * lever_m
        A20 = -cf * sf * AfCt + sf * (BfAt * cf + L)
        A21 = A_w * ct + cf * cf * ct * AfCt + sf * sf * ct * K
        A24 = C_t * cf
        A30 = (-A_w - r_w * (m_f * (cf * r_f + r_w) + mwrw + m_t * (cf * r + r_w))
               - sf * sf * AfCt - cf * (BfAt * cf + L))
        A31 = n_rw * sf * ct * mr_tf + sf * cf * ct * AfCt - cf * sf * ct * K
        A34 = C_t * sf
        A41 = (C2wAt * st + r_f * st * (m_t * (r + cf * r_w) + m_f * (r_f + cf * r_w))
               + rtmt * st * (r + cf * r_w)
               + r_w * st * (mwrw + sf * sf * r_w * Mft
                             + cf * (m_t * (r + cf * r_w) + m_f * (r_f + cf * r_w))))
        A42 = -C_w - rtmt * cf * r_w - rw2_M - r_f * cf * r_w * Mft
        A43 = A13 - r_w * cf * mr_ft

        b0 = -V - C_t * a1
        b1 = -U + CwAt * phd * ct * thd + AfBfAt * w1 * w2 - C_t * w1 * wt + H
        b2 = n_T * ct - A2w * phd * st * thd - C_w * thd * ww + cf * E1 - sf * (E2 + G)
        b3 = (n_Aw * phd * phd * st * ct - C_w * phd * ct * ww
              - r_w * (m_w * phd * ct * ww * r_w - M_g * st + m_f * Q_f + m_t * Q_r)
              + sf * E1 + cf * (E2 + G))
        b4 = (n_T * st + C2wAt * phd * ct * thd + AfBfAt * w1 * w2 - C_t * w1 * wt + H
              + r_w * (m2wrw * phd * ct * thd
                       + sf * (m_f * R_f + m_t * R_r - Mft_g * cf * ct)
                       + cf * (m_f * P_f + m_t * P_r + Mft_g * sf * ct)))
        return A00, A01, A04, A11, A12, A13, A20, A21, A24, A30, A31, A34, A41, A42, A43, b0, b1, b2, b3, b4

    return system


def unicycle_matrices(
    z: Sequence[float], u: Sequence[float], p: UnicycleParams
) -> tuple[list[list[float]], list[float]]:
    """The 5x5 matrix ``A`` and the vector ``b`` with ``[thdd, phdd, psdd_w, psdd_f, psdd_t] = -A^{-1} b``.

    Args:
        z: physical state, 12 floats (only the rates and ``theta``, ``psi_f`` enter).
        u: ``[u_t, u_w]`` torques in Nm (turntable ``V``, wheel ``U`` of the reference).
        p: physical parameters.

    Returns:
        ``(A, b)`` as a 5x5 list of lists and a list of 5 floats (the entries of :func:`unicycle_system`).
    """
    (A00, A01, A04, A11, A12, A13, A20, A21, A24, A30, A31, A34, A41, A42, A43, *b) = unicycle_system(p)(
        z[0], z[1], z[2], z[3], z[4], z[7], z[10], u[0], u[1]
    )
    A = [
        [A00, A01, 0.0, 0.0, A04],
        [0.0, A11, A12, A13, 0.0],
        [A20, A21, 0.0, 0.0, A24],
        [A30, A31, 0.0, 0.0, A34],
        [0.0, A41, A42, A43, 0.0],
    ]
    return A, b


def _solve_blocks(
    a00: float, a01: float, a04: float, a11: float, a12: float, a13: float, a20: float, a21: float, a24: float,
    a30: float, a31: float, a34: float, a41: float, a42: float, a43: float,
    b0: float, b1: float, b2: float, b3: float, b4: float,
) -> tuple[float, float, float, float, float]:
    """``A^{-1} b`` from the nonzero entries of the unicycle's ``A`` (Cramer's rule on the blocks).

    Rows 1, 3, 4 (1-based) of ``A`` involve only ``[thdd, phdd, psdd_t]`` (roll, yaw, turntable);
    rows 2 and 5 involve ``[phdd, psdd_w, psdd_f]``. So a 3x3 system gives roll, yaw and turntable
    accelerations, then a 2x2 system the wheel and pitch accelerations, and
    ``det A = det(3x3 block) * det(2x2 block)`` (up to sign). A singular block gives NaN,
    which the environment reports as a :class:`~harness.errors.NumericalError`.
    """
    # 3x3: [[a00 a01 a04], [a20 a21 a24], [a30 a31 a34]] [thdd, phdd, ptdd] = [b0, b2, b3]
    c0 = a21 * a34 - a24 * a31
    c1 = a20 * a34 - a24 * a30
    c2 = a20 * a31 - a21 * a30
    det3 = a00 * c0 - a01 * c1 + a04 * c2
    if det3 == 0.0:
        return _NAN5
    x0 = (b0 * c0 - a01 * (b2 * a34 - a24 * b3) + a04 * (b2 * a31 - a21 * b3)) / det3
    x1 = (a00 * (b2 * a34 - a24 * b3) - b0 * c1 + a04 * (a20 * b3 - b2 * a30)) / det3
    x4 = (a00 * (a21 * b3 - b2 * a31) - a01 * (a20 * b3 - b2 * a30) + b0 * c2) / det3
    # 2x2: [[a12 a13], [a42 a43]] [pwdd, pfdd] = [b1 - a11 phdd, b4 - a41 phdd]
    det2 = a12 * a43 - a13 * a42
    if det2 == 0.0:
        return _NAN5
    r1, r4 = b1 - a11 * x1, b4 - a41 * x1
    x2 = (r1 * a43 - a13 * r4) / det2
    x3 = (a12 * r4 - r1 * a42) / det2
    return x0, x1, x2, x3, x4


_NAN5 = (math.nan,) * 5


def _solve_accelerations(A: list[list[float]], b: list[float]) -> list[float]:
    """``A^{-1} b`` for a dense 5x5 ``A`` of the unicycle's sparsity pattern (:func:`_solve_blocks`)."""
    (a00, a01, _, _, a04), (_, a11, a12, a13, _), (a20, a21, _, _, a24), (a30, a31, _, _, a34), \
        (_, a41, a42, a43, _) = A
    return list(_solve_blocks(a00, a01, a04, a11, a12, a13, a20, a21, a24, a30, a31, a34, a41, a42, a43, *b))


def unicycle_rhs(z: Sequence[float], u: Sequence[float], p: UnicycleParams) -> tuple[float, ...]:
    """dz/dt of the 12 ODE states for torques ``u = [u_t, u_w]`` (Nm); 12 floats in, 12 out."""
    acc = _solve_blocks(*unicycle_system(p)(z[0], z[1], z[2], z[3], z[4], z[7], z[10], u[0], u[1]))
    phi, pwd = z[8], z[2]
    return (
        -acc[0], -acc[1], -acc[2], -acc[3], -acc[4],
        p.r_w * math.cos(phi) * pwd, p.r_w * math.sin(phi) * pwd,
        z[0], z[1], z[2], z[3], z[4],
    )


def _no_jit(function: Callable) -> Callable:
    return function


def _falling_derivative(p: UnicycleParams, fall_angle: float, jit: Callable = _no_jit) -> Callable[..., tuple[float, ...]]:
    """``deriv(thd, phd, pwd, pfd, ptd, theta, phi, psi_f, u_t, u_w) -> dz/dt`` (12 floats) with the fall
    region absorbing: the right-hand side of :func:`falling_rhs` on the eight state entries it reads.

    ``jit`` compiles ``deriv`` and the functions it calls (``numba.njit`` in :func:`unicycle_stepper`);
    the default leaves them plain Python."""
    system, solve, r_w, cos, sin = jit(unicycle_system(p)), jit(_solve_blocks), p.r_w, math.cos, math.sin

    def deriv(thd: float, phd: float, pwd: float, pfd: float, ptd: float, th: float, phi: float, pf: float,
              V: float, U: float) -> tuple[float, ...]:
        if abs(th) > fall_angle or abs(pf) > fall_angle:
            return _FROZEN
        x0, x1, x2, x3, x4 = solve(*system(thd, phd, pwd, pfd, ptd, th, pf, V, U))
        return (-x0, -x1, -x2, -x3, -x4, r_w * cos(phi) * pwd, r_w * sin(phi) * pwd, thd, phd, pwd, pfd, ptd)

    return jit(deriv)


def falling_rhs(p: UnicycleParams, fall_angle: float) -> RightHandSide:
    """The task's right-hand side: :func:`unicycle_rhs`, with the fall region made absorbing.

    Where ``|theta| > fall_angle`` or ``|psi_f| > fall_angle`` (fallen; the task uses pi/2) the
    derivative is zero. The episode ends there anyway; freezing the state keeps RK4 from stepping
    through the singularity of ``A`` at ``|theta| = pi/2`` (where it diverges), and a fall in the
    middle of a control step is not undone by the end of the step (in Euler angles, a unicycle that
    passes ``theta = pi/2`` comes back with ``theta`` below ``pi/2`` and yaw turned by ``pi``).
    Elsewhere the same floats as :func:`unicycle_rhs`.
    """
    deriv = _falling_derivative(p, fall_angle)

    def rhs(z: Sequence[float], u: Sequence[float]) -> tuple[float, ...]:
        return deriv(z[0], z[1], z[2], z[3], z[4], z[7], z[8], z[10], u[0], u[1])

    return rhs


def _rk4_core(deriv: Callable[..., tuple[float, ...]]) -> Callable[..., tuple[float, ...]]:
    """``core(12 states, u_t, u_w, dt, substeps) -> 12 states``: ``substeps`` RK4 steps of ``deriv`` on scalars."""

    def core(thd: float, phd: float, pwd: float, pfd: float, ptd: float, x: float, y: float, th: float, phi: float,
             psw: float, pf: float, pst: float, V: float, U: float, dt: float, substeps: int) -> tuple[float, ...]:
        h = dt / substeps
        half, sixth = 0.5 * h, h / 6.0
        for _ in range(substeps):
            # k1 = a, k2 = b, k3 = c, k4 = d: (5 accelerations, xdot, ydot, 5 angle rates) each
            a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11 = deriv(thd, phd, pwd, pfd, ptd, th, phi, pf, V, U)
            b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11 = deriv(
                thd + half * a0, phd + half * a1, pwd + half * a2, pfd + half * a3, ptd + half * a4,
                th + half * a7, phi + half * a8, pf + half * a10, V, U)
            c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11 = deriv(
                thd + half * b0, phd + half * b1, pwd + half * b2, pfd + half * b3, ptd + half * b4,
                th + half * b7, phi + half * b8, pf + half * b10, V, U)
            d0, d1, d2, d3, d4, d5, d6, d7, d8, d9, d10, d11 = deriv(
                thd + h * c0, phd + h * c1, pwd + h * c2, pfd + h * c3, ptd + h * c4,
                th + h * c7, phi + h * c8, pf + h * c10, V, U)
            thd, phd, pwd, pfd, ptd, x, y, th, phi, psw, pf, pst = (
                thd + sixth * (a0 + 2.0 * (b0 + c0) + d0),
                phd + sixth * (a1 + 2.0 * (b1 + c1) + d1),
                pwd + sixth * (a2 + 2.0 * (b2 + c2) + d2),
                pfd + sixth * (a3 + 2.0 * (b3 + c3) + d3),
                ptd + sixth * (a4 + 2.0 * (b4 + c4) + d4),
                x + sixth * (a5 + 2.0 * (b5 + c5) + d5),
                y + sixth * (a6 + 2.0 * (b6 + c6) + d6),
                th + sixth * (a7 + 2.0 * (b7 + c7) + d7),
                phi + sixth * (a8 + 2.0 * (b8 + c8) + d8),
                psw + sixth * (a9 + 2.0 * (b9 + c9) + d9),
                pf + sixth * (a10 + 2.0 * (b10 + c10) + d10),
                pst + sixth * (a11 + 2.0 * (b11 + c11) + d11),
            )
        return thd, phd, pwd, pfd, ptd, x, y, th, phi, psw, pf, pst

    return core


def numba_available() -> bool:
    """Whether :func:`unicycle_stepper` compiles its arithmetic (numba installed, ``HARNESS_NO_JIT`` unset)."""
    if os.environ.get("HARNESS_NO_JIT"):
        return False
    return importlib.util.find_spec("numba") is not None


@lru_cache(maxsize=None)
def unicycle_stepper(p: UnicycleParams, fall_angle: float, compiled: bool | None = None) -> Stepper:
    """``step(z, u, dt, substeps)``: ``rk4_zoh(falling_rhs(p, fall_angle), z, u, dt, substeps)`` on scalars.

    The same arithmetic as :func:`tasks.simulation.rk4_zoh` (bit-identical results) without the
    per-stage lists: the right-hand side reads only the five rates and ``theta, phi, psi_f``, so
    only those enter the stage states; all 12 entries get the RK4 update. ``z``: the 12 ODE
    states (units in the module docstring); ``u = [u_t, u_w]`` (Nm); ``dt`` in s. Returns 12 floats.

    ``compiled`` (default: :func:`numba_available`): the same Python source compiled by
    ``numba.njit`` (extra ``fast``; IEEE arithmetic, no fast-math, so the states equal the plain
    Python ones, ``tests/tasks/test_unicycle.py``), ~10x more steps per second; the first step of
    a process pays the compilation (a few seconds). Without numba the source runs as Python.
    """
    if compiled is None:
        compiled = numba_available()
    jit = _no_jit
    if compiled:
        import numba

        from harness.vector_width import configure

        configure()  # numba's target is shared: its vector width before its first function (no fast-math: same bits)
        jit = numba.njit(cache=False)
    core = jit(_rk4_core(_falling_derivative(p, fall_angle, jit)))

    def step(z: Sequence[float], u: Sequence[float], dt: float, substeps: int) -> list[float]:
        return list(core(*map(float, z), float(u[0]), float(u[1]), float(dt), int(substeps)))

    return step


_FROZEN = (0.0,) * 12


def observation_from_physical(z: np.ndarray) -> np.ndarray:
    """The 10 planning states from the 12 ODE states; ``(..., 12) -> (..., 10)``.

    ``[x_c, y_c] = -R(phi) [x, y]`` with ``R(phi) = [[cos, sin], [-sin, cos]]``.
    """
    z = np.asarray(z, dtype=np.float64)
    x, y, phi = z[..., 5], z[..., 6], z[..., 8]
    c, s = np.cos(phi), np.sin(phi)
    x_c = -(c * x + s * y)
    y_c = s * x - c * y
    return np.concatenate([z[..., 0:5], x_c[..., None], y_c[..., None], z[..., 7:9], z[..., 10:11]], axis=-1)


def physical_from_observation(x: np.ndarray, psi_w: float = 0.0, psi_t: float = 0.0) -> list[float]:
    """The 12 ODE states from the 10 planning states (inverse of :func:`observation_from_physical`).

    ``[x, y] = -R(phi)^T [x_c, y_c]``; the unobserved cyclic angles ``psi_w, psi_t`` (which the
    dynamics do not depend on) are set to the given values.
    """
    x = np.asarray(x, dtype=np.float64)
    x_c, y_c, phi = float(x[5]), float(x[6]), float(x[8])
    c, s = math.cos(phi), math.sin(phi)
    px = -(c * x_c - s * y_c)
    py = -(s * x_c + c * y_c)
    return [*map(float, x[0:5]), px, py, float(x[7]), phi, psi_w, float(x[9]), psi_t]


def top_offset(theta: np.ndarray, psi_f: np.ndarray, p: UnicycleParams) -> np.ndarray:
    """Displacement of the top (turntable centre) from its upright position, metres.

    The upright top is ``r_w + r`` straight above the wheel contact point. Returns ``(..., 3)``
    with [height deficit ``r_w + r - (r_w + r cos psi_f) cos theta``, sideways offset
    ``(r_w + r cos psi_f) sin theta``, along-heading offset ``r sin psi_f``].
    """
    theta, psi_f = np.asarray(theta, dtype=np.float64), np.asarray(psi_f, dtype=np.float64)
    lever = p.r_w + p.r * np.cos(psi_f)
    return np.stack(
        [p.r_w + p.r - lever * np.cos(theta), lever * np.sin(theta), p.r * np.sin(psi_f)], axis=-1
    )


def _frame_vectors(z: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (world frame) ``f`` (roll axis), ``a`` (wheel axle), ``n`` (in-plane up), ``d`` (frame)."""
    th, phi, pf = z[7], z[8], z[10]
    ez = np.array([0.0, 0.0, 1.0])
    f = -np.array([math.cos(phi), math.sin(phi), 0.0])
    lat = np.cross(f, ez)
    n = math.cos(th) * ez + math.sin(th) * lat
    a = -math.sin(th) * ez + math.cos(th) * lat
    d = -math.sin(pf) * f + math.cos(pf) * n
    return f, a, n, d


def body_points(z: Sequence[float], p: UnicycleParams) -> dict[str, np.ndarray]:
    """World positions (m) of the contact point, wheel centre, frame centre of mass and top."""
    _, _, n, d = _frame_vectors(z)
    contact = np.array([z[5], z[6], 0.0])
    wheel = contact + p.r_w * n
    return {"contact": contact, "wheel": wheel, "frame": wheel + p.r_f * d, "top": wheel + p.r * d}


def total_energy(z: Sequence[float], p: UnicycleParams) -> float:
    """Kinetic plus potential energy (J) of wheel, frame and turntable; zero potential at the floor.

    Angular velocities (world frame): the roll frame turns with ``phidot e_z + thetadot f``; the
    wheel adds ``psidot_w a``, the frame ``psidot_f a``, the turntable additionally
    ``psidot_t d`` about the frame's long axis ``d``. Body inertias: wheel ``C_w`` (axle) and
    ``A_w``; frame ``C_f`` (axle), ``A_f`` (long axis ``d``), ``B_f`` (the third axis);
    turntable ``C_t`` (``d``) and ``A_t``. The contact point moves with the rolling constraint.
    """
    f, a, n, d = _frame_vectors(z)
    thd, phd, pwd, pfd, ptd = z[0], z[1], z[2], z[3], z[4]
    ez = np.array([0.0, 0.0, 1.0])
    w_roll = phd * ez + thd * f
    w_wheel = w_roll + pwd * a
    w_frame = w_roll + pfd * a
    w_turn = w_frame + ptd * d
    e3 = np.cross(a, d)  # third frame axis
    v_contact = p.r_w * pwd * np.array([math.cos(z[8]), math.sin(z[8]), 0.0])
    v_wheel = v_contact + p.r_w * np.cross(w_roll, n)
    v_frame = v_wheel + p.r_f * np.cross(w_frame, d)
    v_top = v_wheel + p.r * np.cross(w_frame, d)
    pts = body_points(z, p)

    def rot(w: np.ndarray, axes_moments: list[tuple[np.ndarray, float]]) -> float:
        return 0.5 * sum(moment * float(w @ axis) ** 2 for axis, moment in axes_moments)

    kinetic = (
        0.5 * p.m_w * float(v_wheel @ v_wheel) + rot(w_wheel, [(a, p.C_w), (n, p.A_w), (np.cross(a, n), p.A_w)])
        + 0.5 * p.m_f * float(v_frame @ v_frame) + rot(w_frame, [(a, p.C_f), (d, p.A_f), (e3, p.B_f)])
        + 0.5 * p.m_t * float(v_top @ v_top) + rot(w_turn, [(d, p.C_t), (a, p.A_t), (e3, p.A_t)])
    )
    potential = p.g * (p.m_w * pts["wheel"][2] + p.m_f * pts["frame"][2] + p.m_t * pts["top"][2])
    return float(kinetic + potential)


def initial_distribution(init: str) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(12,)`` and covariance ``(12, 12)`` of the initial ODE state for an ``init`` variant.

    * ``"paper"``: ``Sigma0 = 0.25^2 I`` as in ICML 2011 ("each angle off by about 30 degrees,
      twice the standard deviation"). Interpretation: the identity covers all 12 ODE states, i.e.
      std 0.25 rad/s on the five rates, 0.25 m on the contact position ``x, y`` and 0.25 rad on the
      five angles.
    * ``"code"``: ``settings_unicycle.m``: stds ``[.02 .02 .02 .02 .02 .1 .1 .02 .02 .02 .02 .02]``
      (0.1 m on ``x, y``, 0.02 on every rate and angle).

    The mean is zero (upright, at the lab origin, heading along the x axis) in both.
    """
    if init == "paper":
        std = np.full(12, 0.25)
    elif init == "code":
        std = np.array([0.02] * 5 + [0.1, 0.1] + [0.02] * 5)
    else:
        raise ValueError(f"unknown unicycle init variant {init!r}; expected 'paper' or 'code'")
    return np.zeros(12), np.diag(std**2)


@lru_cache(maxsize=None)
def _observation_init_moments(init: str) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(10,)`` and covariance ``(10, 10)`` of the initial distribution in observation coordinates.

    As the reference (which uses 1000 samples): Monte-Carlo through the observation map
    (:data:`INIT_MC_SAMPLES` samples, seed :data:`INIT_MC_SEED`, so the result is the same on every
    call and machine), then the entries that are plain copies of ODE states (rates, ``theta``,
    ``phi``, ``psi_f``) are overwritten with their exact moments; only the moments involving
    ``x_c, y_c`` come from the samples.
    """
    mean12, cov12 = initial_distribution(init)
    rng = np.random.default_rng(INIT_MC_SEED)
    z = mean12 + rng.standard_normal((INIT_MC_SAMPLES, 12)) @ np.linalg.cholesky(cov12).T
    obs = observation_from_physical(z)
    mean = obs.mean(axis=0)
    cov = np.cov(obs, rowvar=False)
    ident, src = np.array(OBS_IDENTITY), np.array(OBS_FROM_ODE)
    mean[ident] = mean12[src]
    cov[np.ix_(ident, ident)] = cov12[np.ix_(src, src)]
    cov = 0.5 * (cov + cov.T)
    mean.setflags(write=False)
    cov.setflags(write=False)
    return mean, cov


def unicycle_cost(r_w: float = 0.22, r: float = 0.81, width: float = 1.0) -> SaturatingCost:
    """The reference's ``loss_unicycle`` as a :class:`~harness.task.SaturatingCost` on the 10 observed states.

    ``c = 1 - exp(-1/2 [8 h^2 + 1/2 (x_c - r sin psi_f)^2 + 1/2 (y_c - (r + r_w) sin theta)^2
    + phi^2 / (16 pi^2)] / width^2)`` with the height deficit of the top
    ``h = r_w cos theta + (r/2) cos(theta - psi_f) + (r/2) cos(theta + psi_f) - r_w - r``.

    Cost features: angles ``[theta, alpha = theta - psi_f, beta = theta + psi_f, psi_f]``
    (``angle_map``); the residual rows are the four bracketed terms scaled by the square roots of
    their weights 8, 1/2, 1/2, 1/(16 pi^2). ``r_w = 0.22`` and ``r = 0.81`` are the reference's
    ``cost.p`` (the ODE's wheel radius is 0.225).
    """
    d, k = 10, 4
    th, ph, pf, xc, yc = 7, 8, 9, 5, 6
    angle_map = np.zeros((k, d))
    angle_map[0, th] = 1.0
    angle_map[1, th], angle_map[1, pf] = 1.0, -1.0
    angle_map[2, th], angle_map[2, pf] = 1.0, 1.0
    angle_map[3, pf] = 1.0
    sin0, cos0 = d, d + k  # feature columns of sin(angle_j) and cos(angle_j) are sin0 + j, cos0 + j
    linear_map = np.zeros((4, d + 2 * k))
    target = np.zeros(4)
    w = math.sqrt(8.0)
    linear_map[0, cos0 + 0] = w * r_w
    linear_map[0, cos0 + 1] = w * r / 2
    linear_map[0, cos0 + 2] = w * r / 2
    target[0] = w * (r_w + r)
    w = math.sqrt(0.5)
    linear_map[1, xc], linear_map[1, sin0 + 3] = w, -w * r
    linear_map[2, yc], linear_map[2, sin0 + 0] = w, -w * (r + r_w)
    linear_map[3, ph] = 1.0 / (4.0 * math.pi)
    return SaturatingCost(angle_map=angle_map, linear_map=linear_map, target=target, width=width)


class UnicycleEnv(OdeEnv):
    """:class:`~tasks.simulation.OdeEnv` whose start state is drawn on the 12 ODE states.

    ``reset`` samples ``z0 ~ N(mu0, Sigma0)`` of the chosen ``init`` variant (not the Gaussian
    summary ``spec.init_mean, spec.init_cov`` of the observation) and starts from its observation.
    The unobserved cyclic angles ``psi_w, psi_t`` start at 0 (the dynamics do not depend on them).
    ``reset(options={"state": x0})`` starts from a given observation-coordinate state ``x0``.
    """

    def __init__(self, spec: TaskSpec, init_mean12: np.ndarray, init_cov12: np.ndarray, **kwargs) -> None:
        super().__init__(spec, **kwargs)
        self._mean12 = np.asarray(init_mean12, dtype=np.float64)
        self._chol12 = np.linalg.cholesky(init_cov12)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if options and options.get("state") is not None:
            return super().reset(seed=seed, options=options)
        gym.Env.reset(self, seed=seed)
        z0 = self._mean12 + self._chol12 @ self.np_random.standard_normal(12)
        return super().reset(options={**(options or {}), "state": observation_from_physical(z0)})


class Unicycle(Task):
    """Robotic unicycle balancing (PILCO, ICML 2011 §5; reference implementation ``scenarios/unicycle``).

    Observation: the 10 planning states ``[thetadot, phidot, psidot_w, psidot_f, psidot_t, x_c, y_c,
    theta, phi, psi_f]`` (see the module docstring); controls ``[u_t, u_w]`` = turntable and wheel
    torques, ``|u_t| <= 10``, ``|u_w| <= 50`` Nm; ``dt = 0.15`` s, 67 steps (10 s). The episode
    terminates when the unicycle falls: ``|theta| > pi/2`` or ``|psi_f| > pi/2`` (the reference's
    constraint); in the simulation the fall region is absorbing (:func:`falling_rhs`). A fall passes close
    to the singularity of ``A``, so about 1 % of the terminal states carry rates above 100 rad/s
    (measured with uniformly random torques from the ``paper`` start); the reference drops the
    transition that violates the constraint from its training data.

    Angles: ``theta``, ``phi`` and ``psi_f`` (observation indices 7, 8, 9) are angles, but, as the
    reference (``angi = []``), ``spec.angle_indices`` is empty: before a fall they stay within
    +-pi/2 and the reference models them without sin/cos.

    Start: option ``init`` (:func:`initial_distribution`): ``"code"`` (default) the reference
    code's ``Sigma0`` (std 0.02 on rates and angles, 0.1 m on position), ``"paper"`` the ICML text's
    ``0.25^2 I`` on the 12 ODE states. The default is the one from which the task is solvable by
    the paper's linear policy (see the control structure below); ``paper`` is kept as a variant.
    ``spec.init_mean, spec.init_cov`` are its moments in observation coordinates
    (:func:`_observation_init_moments`). Measurement noise: std 0.01 on the five rates, 0.003 on
    the other five entries, times option ``measurement_noise``.

    Cost: :func:`unicycle_cost` (the reference's ``loss_unicycle``, width 1).

    Control structure (:mod:`tasks.unicycle_lqr`, ``tests/tasks/test_unicycle.py``): upright and at
    rest, neither torque enters the roll acceleration to first order (the turntable yaws, the wheel
    pitches), so the falling roll mode (time constant ~0.3 s) cannot be stabilised by linear
    feedback about rest. A linear policy balances only about a moving equilibrium, e.g. riding
    forward (a bias in ``W x + b``), where forward speed times yaw rate gives the roll torque. A
    discrete LQR about riding at 0.5-1.5 m/s, applied as the PILCO linear controller with trapezoid
    squashing, succeeds in 100 % of 1000 episodes from ``init="code"`` but in at most 65 % from
    ``init="paper"`` (the failures start with large roll or pitch;
    ``results/benchmarks/unicycle_linear_ceiling.md``); a linear policy searched by CMA-ES on the
    true simulator from there reaches 86 % (``results/benchmarks/unicycle_cmaes_ceiling_paper.md``).
    Riding away also makes the cost grow (``x_c``): from ``init="paper"`` the 1 m/s LQR's evaluation
    cost (58.2 of 67) is close to that of falling at once (62.3).

    Success: the episode ran all ``horizon`` steps without a fall, and at its final true state the
    top of the frame (turntable centre) is within 0.10 m of its upright position, the point
    ``r_w + r = 1.035`` m straight above the wheel's contact point: ``|top_offset(theta, psi_f)|
    <= 0.10`` with :func:`top_offset` = (height deficit, sideways offset, along-heading offset)
    computed with the ODE's geometry (``r_w = 0.225``, ``r = 0.81``).
    """

    name = "unicycle"
    description = "Robotic unicycle balancing, PILCO reference implementation (12 ODEs, dt=0.15 s, 10 s)"
    options = (
        Option("init", str, "code", "initial distribution: code (settings_unicycle.m; default: a linear policy can "
               "ride from it) or paper (0.25^2 I, the ICML text; riding LQRs reach 65 %, a CMA-ES linear policy 86 %)",
               choices=("code", "paper")),
        Option("horizon", int, 67, "control steps per episode (dt = 0.15 s)", low=1),
        Option("measurement_noise", float, 1.0,
               "scale of the observation noise stds (0.01 on rates, 0.003 on the rest); 0 = none", low=0.0),
        Option("substeps", int, round(SUBSTEPS_PER_SECOND * 0.15),
               "RK4 sub-steps per 0.15 s control step (accuracy vs speed; see tasks.unicycle)", low=1),
    )

    dt = 0.15
    torque_limits = (10.0, 50.0)
    fall_angle = math.pi / 2
    success_radius = 0.10

    def __init__(self, **options) -> None:
        super().__init__(**options)
        self.params = UnicycleParams()
        self.init_mean12, self.init_cov12 = initial_distribution(self.options["init"])
        #: ``f(z, u) -> dz/dt``: :func:`unicycle_rhs` with the fall region absorbing (:func:`falling_rhs`).
        self.rhs = falling_rhs(self.params, self.fall_angle)
        #: the env's integrator: :func:`unicycle_stepper`, the same steps as ``rk4_zoh(self.rhs, ...)``.
        self.stepper = unicycle_stepper(self.params, self.fall_angle)
        self._spec = self._build_spec()

    def _build_spec(self) -> TaskSpec:
        mean, cov = _observation_init_moments(self.options["init"])
        noise = np.array([0.01] * 5 + [0.003] * 5) * self.options["measurement_noise"]
        return TaskSpec(
            name=self.name,
            state_names=STATE_NAMES,
            action_names=ACTION_NAMES,
            dt=self.dt,
            horizon=self.options["horizon"],
            action_low=-np.array(self.torque_limits),
            action_high=np.array(self.torque_limits),
            init_mean=mean.copy(),
            init_cov=cov.copy(),
            angle_indices=(),
            cost=unicycle_cost(),
            measurement_noise_std=noise,
            options=dict(self.options),
            physical_state_dim=12,
        )

    @property
    def spec(self) -> TaskSpec:
        return self._spec

    def fallen(self, state: np.ndarray) -> bool:
        """``|theta| > pi/2`` or ``|psi_f| > pi/2`` for an observation-coordinate state ``(10,)``."""
        return bool(abs(state[7]) > self.fall_angle or abs(state[9]) > self.fall_angle)

    def make_env(self, render_mode: str | None = None, measurement_noise: bool = True) -> UnicycleEnv:
        return UnicycleEnv(
            self._spec,
            self.init_mean12,
            self.init_cov12,
            rhs=self.rhs,
            stepper=self.stepper,
            substeps=self.options["substeps"],
            left_region=self.fallen,
            draw=self.draw,
            render_mode=render_mode,
            measurement_noise=measurement_noise and self.options["measurement_noise"] > 0,
            physical_from_state=physical_from_observation,
            state_from_physical=observation_from_physical,
        )

    def top_distance(self, state: np.ndarray) -> float:
        """Distance (m) of the top from its upright position for an observation-coordinate state."""
        return float(np.linalg.norm(top_offset(state[7], state[9], self.params)))

    def goal_distance(self, state: np.ndarray) -> float:
        return self.top_distance(np.asarray(state))

    def success(self, episode: Episode) -> bool:
        if episode.terminated or episode.steps < self._spec.horizon:
            return False
        states = np.asarray(episode.states)
        if any(self.fallen(s) for s in states):
            return False
        return self.top_distance(states[-1]) <= self.success_radius

    def draw(self, state: np.ndarray) -> np.ndarray:
        """RGB image, two views in the unicycle's own frame: from the side (left) and from behind (right).

        Side view: along-heading offset vs height (shows the pitch ``psi_f``); rear view: sideways
        offset vs height (shows the roll ``theta``). Red dot: the upright top position.
        """
        p = self.params
        th, pf = float(state[7]), float(state[9])
        st, ct, sf, cf = math.sin(th), math.cos(th), math.sin(pf), math.cos(pf)
        lever = p.r_w + p.r * cf
        wheel_h, top_h = p.r_w * ct, lever * ct
        side_shift = 2.6
        canvas = Canvas((-1.3, 1.3 + side_shift), (-0.15, 1.3), width=560)
        grey, frame_c, wheel_c, target_c = (120, 120, 120), (200, 140, 40), (60, 60, 60), (230, 60, 60)
        for x0 in (0.0, side_shift):
            canvas.segment((x0 - 1.2, -0.01), (x0 + 1.2, -0.01), 0.01, grey)
            canvas.disc(x0, p.r_w + p.r, 0.03, target_c)
        # side view: the wheel is a disc, the frame goes from the axle to the top
        canvas.disc(0.0, wheel_h, p.r_w, wheel_c)
        canvas.segment((0.0, wheel_h), (p.r * sf, top_h), 0.04, frame_c)
        canvas.disc(p.r * sf, top_h, 0.05, (90, 90, 200))
        # rear view: the wheel is seen edge-on
        canvas.segment((side_shift, 0.0), (side_shift + 2 * p.r_w * st, 2 * wheel_h), 0.04, wheel_c)
        canvas.segment((side_shift + p.r_w * st, wheel_h), (side_shift + lever * st, top_h), 0.04, frame_c)
        canvas.segment((side_shift + lever * st - 0.2 * ct, top_h + 0.2 * st),
                       (side_shift + lever * st + 0.2 * ct, top_h - 0.2 * st), 0.03, (90, 90, 200))
        return canvas.image


def make_gym_env(render_mode: str | None = None, **options) -> UnicycleEnv:
    """Entry point of ``gymnasium.make("harness/Unicycle-v0", **options)``."""
    return Unicycle(**options).make_env(render_mode=render_mode)
