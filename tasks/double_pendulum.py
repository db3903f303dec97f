"""Cart-double-pendulum swing-up as in the PILCO reference implementation (``scenarios/cartDoublePendulum``).

State ``x = [x, xdot, th1dot, th2dot, th1, th2]`` (m, m/s, rad/s, rad/s, rad, rad) with absolute
link angles, ``theta = 0`` **upright**; one control: the horizontal force on the cart (N). Two
uniform links (masses ``m2, m3``, lengths ``l2, l3``) hang in series from the cart (mass ``m1``),
which feels viscous friction ``b xdot``. The accelerations solve ``A [xdd, th1dd, th2dd]^T = r``::

    A = [[ 2(m1+m2+m3),         -(m2+2m3) l2 cos th1,  -m3 l3 cos th2        ],
         [ -(3m2+6m3) cos th1,   (2m2+6m3) l2,          3 m3 l3 cos(th1-th2)  ],
         [ -3 cos th2,           3 l2 cos(th1-th2),     2 l3                  ]]
    r = [ 2f - 2b xd - (m2+2m3) l2 th1d^2 sin th1 - m3 l3 th2d^2 sin th2,
          (3m2+6m3) g sin th1 - 3 m3 l3 th2d^2 sin(th1-th2),
          3 l2 th1d^2 sin(th1-th2) + 3 g sin th2 ]

(``dynamics_cdp.m``; ``tests/tasks/test_double_pendulum.py`` re-derives them from a sympy
Lagrangian.) The joint is at ``(x - l2 sin th1, l2 cos th1)``, the tip of the second link at
``(x - l2 sin th1 - l3 sin th2, l2 cos th1 + l3 cos th2)``; the goal is the tip at ``(0, l2 + l3)``.

Cost link lengths: the reference's ``loss_cdp.m`` measures the tip with links of **1 m**
(``cost.p = [1 1]``) while the ODE's links are 0.6 m. This task uses the **true 0.6 m** by default,
because the cost should measure the real distance of the tip from its target (and the success
criterion does); ``cost_link_length=1.0`` reproduces the reference code's cost.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from harness.options import Option
from harness.task import Episode, SaturatingCost, TaskSpec
from tasks.drawing import Canvas
from tasks.simulation import OdeEnv, OdeTask, RightHandSide, Stepper
from tasks.success import SUCCESS_RULES, held_within


@dataclass(frozen=True)
class DoublePendulumParams:
    """Physical parameters (SI units); defaults are ``dynamics_cdp.m``."""

    cart_mass: float = 0.5  # m1, kg
    link1_mass: float = 0.5  # m2, kg
    link2_mass: float = 0.5  # m3, kg
    link1_length: float = 0.6  # l2, m
    link2_length: float = 0.6  # l3, m
    friction: float = 0.1  # b, N/(m/s)
    gravity: float = 9.82  # g, m/s^2


def double_pendulum_accelerations(
    params: DoublePendulumParams,
) -> Callable[[float, float, float, float, float, float], tuple[float, float, float]]:
    """``accel(xd, th1d, th2d, th1, th2, f) -> (xdd, th1dd, th2dd)``: ``A^{-1} r`` of the module docstring.

    Units: m/s, rad/s, rad/s, rad, rad, N in; m/s^2, rad/s^2, rad/s^2 out. Returns a closure over
    the parameters; the 3x3 system is solved with the adjugate (Cramer).
    """
    m1, m2, m3 = params.cart_mass, params.link1_mass, params.link2_mass
    l2, l3, b, g = params.link1_length, params.link2_length, params.friction, params.gravity
    a11, a22, a33 = 2.0 * (m1 + m2 + m3), (2.0 * m2 + 6.0 * m3) * l2, 2.0 * l3
    p12, p13 = -(m2 + 2.0 * m3) * l2, -m3 * l3  # a12 = p12 cos th1, a13 = p13 cos th2
    p21, p23, p32 = -(3.0 * m2 + 6.0 * m3), 3.0 * m3 * l3, 3.0 * l2  # a21, a23, a32 factors
    q2, q3 = (3.0 * m2 + 6.0 * m3) * g, 3.0 * g
    sin, cos = math.sin, math.cos

    def accel(xd: float, w1: float, w2: float, th1: float, th2: float, f: float) -> tuple[float, float, float]:
        s1, c1, s2, c2 = sin(th1), cos(th1), sin(th2), cos(th2)
        s12, c12 = sin(th1 - th2), cos(th1 - th2)
        a12, a13, a21, a23, a31, a32 = p12 * c1, p13 * c2, p21 * c1, p23 * c12, -3.0 * c2, p32 * c12
        w1s, w2s = w1 * w1, w2 * w2
        r1 = 2.0 * (f - b * xd) + p12 * w1s * s1 + p13 * w2s * s2
        r2 = q2 * s1 - p23 * w2s * s12
        r3 = p32 * w1s * s12 + q3 * s2
        c11, c12_, c13 = a22 * a33 - a23 * a32, a23 * a31 - a21 * a33, a21 * a32 - a22 * a31
        inv_det = 1.0 / (a11 * c11 + a12 * c12_ + a13 * c13)
        return (
            (c11 * r1 + (a13 * a32 - a12 * a33) * r2 + (a12 * a23 - a13 * a22) * r3) * inv_det,
            (c12_ * r1 + (a11 * a33 - a13 * a31) * r2 + (a13 * a21 - a11 * a23) * r3) * inv_det,
            (c13 * r1 + (a12 * a31 - a11 * a32) * r2 + (a11 * a22 - a12 * a21) * r3) * inv_det,
        )

    return accel


def double_pendulum_rhs(params: DoublePendulumParams) -> RightHandSide:
    """The right-hand side ``f(z, u) -> dz/dt`` for ``z = [x, xd, th1d, th2d, th1, th2]``, force ``u = [f]`` (N)."""
    accel = double_pendulum_accelerations(params)

    def rhs(z: Sequence[float], u: Sequence[float]) -> tuple[float, ...]:
        _, xd, w1, w2, th1, th2 = z
        xdd, w1d, w2d = accel(xd, w1, w2, th1, th2, u[0])
        return (xd, xdd, w1d, w2d, w1, w2)

    return rhs


def double_pendulum_stepper(params: DoublePendulumParams) -> Stepper:
    """``step(z, u, dt, substeps)``: ``rk4_zoh(double_pendulum_rhs(params), z, u, dt, substeps)`` on scalars.

    The same arithmetic as :func:`tasks.simulation.rk4_zoh` (bit-identical results): the RK4
    stage derivatives of ``x, th1, th2`` are the stage velocities, and the accelerations do not
    depend on ``x``, so only :func:`double_pendulum_accelerations` is called.
    ``z``: 6 floats ``[x, xd, th1d, th2d, th1, th2]``; ``u``: ``[f]`` (N); ``dt`` in s. Returns 6 floats.
    """
    accel = double_pendulum_accelerations(params)

    def step(z: Sequence[float], u: Sequence[float], dt: float, substeps: int) -> list[float]:
        x, xd, w1, w2, th1, th2 = map(float, z)
        f = float(u[0])
        h = dt / substeps
        half, sixth = 0.5 * h, h / 6.0
        for _ in range(substeps):
            a1, p1, q1 = accel(xd, w1, w2, th1, th2, f)  # k1 = (xd, a1, p1, q1, w1, w2)
            xd2, w12, w22 = xd + half * a1, w1 + half * p1, w2 + half * q1
            a2, p2, q2 = accel(xd2, w12, w22, th1 + half * w1, th2 + half * w2, f)  # k2 = (xd2, a2, p2, q2, w12, w22)
            xd3, w13, w23 = xd + half * a2, w1 + half * p2, w2 + half * q2
            a3, p3, q3 = accel(xd3, w13, w23, th1 + half * w12, th2 + half * w22, f)
            xd4, w14, w24 = xd + h * a3, w1 + h * p3, w2 + h * q3
            a4, p4, q4 = accel(xd4, w14, w24, th1 + h * w13, th2 + h * w23, f)
            x, xd, w1, w2, th1, th2 = (
                x + sixth * (xd + 2.0 * (xd2 + xd3) + xd4),
                xd + sixth * (a1 + 2.0 * (a2 + a3) + a4),
                w1 + sixth * (p1 + 2.0 * (p2 + p3) + p4),
                w2 + sixth * (q1 + 2.0 * (q2 + q3) + q4),
                th1 + sixth * (w1 + 2.0 * (w12 + w13) + w14),
                th2 + sixth * (w2 + 2.0 * (w22 + w23) + w24),
            )
        return [x, xd, w1, w2, th1, th2]

    return step


def double_pendulum_energy(z: Sequence[float], p: DoublePendulumParams) -> float:
    """Total mechanical energy (J), zero potential at the pivot height (``dynamics_cdp.m``, 2 args)."""
    _, xd, w1, w2, th1, th2 = z
    m1, m2, m3 = p.cart_mass, p.link1_mass, p.link2_mass
    l2, l3, g = p.link1_length, p.link2_length, p.gravity
    return (
        (m1 + m2 + m3) * xd**2 / 2
        + (m2 / 6 + m3 / 2) * l2**2 * w1**2
        + m3 * l3**2 * w2**2 / 6
        - (m2 / 2 + m3) * l2 * xd * w1 * math.cos(th1)
        - m3 * l3 * xd * w2 * math.cos(th2) / 2
        + m3 * l2 * l3 * w1 * w2 * math.cos(th1 - th2) / 2
        + (m2 / 2 + m3) * l2 * g * math.cos(th1)
        + m3 * l3 * g * math.cos(th2) / 2
    )


def link_tip(states: np.ndarray, l2: float, l3: float) -> np.ndarray:
    """Tip of the second link ``(x - l2 sin th1 - l3 sin th2, l2 cos th1 + l3 cos th2)``; ``(..., 6)`` -> ``(..., 2)``."""
    states = np.asarray(states, dtype=np.float64)
    th1, th2 = states[..., 4], states[..., 5]
    return np.stack(
        [states[..., 0] - l2 * np.sin(th1) - l3 * np.sin(th2), l2 * np.cos(th1) + l3 * np.cos(th2)], axis=-1
    )


class CartDoublePendulum(OdeTask):
    """Cart-double-pendulum swing-up (reference: dt = 0.05 s, 100 steps = 5 s, |f| <= 20 N).

    Start ``N([0 0 0 0 pi pi], diag([0.1 0.1 0.1 0.1 0.01 0.01]^2))`` (both links hanging down);
    observations carry ``N(0, 0.01^2)`` noise; cost ``1 - exp(-d^2 / (2 * 0.5^2))`` with ``d`` the
    distance of the second link's tip from ``(0, 2 L)``, ``L = cost_link_length`` (default: the
    true 0.6 m; the reference code uses 1 m, see the module docstring).

    Success: the TRUE tip of the second link (``episode.states``, true link lengths) is within
    12 cm of the upright target ``(0, 1.2 m)`` for 10 consecutive recorded states (0.5 s) and the
    episode was not terminated; ``success_rule=final`` asks for the last 10 states instead
    (:mod:`tasks.success`).
    """

    name = "double-pendulum"
    description = "Cart-double-pendulum swing-up, PILCO reference implementation (links 0.6 m, dt=0.05 s, 5 s)"
    options = (
        Option("horizon", int, 100, "control steps per episode (dt = 0.05 s)", low=10),
        Option("measurement_noise", float, 0.01, "std of the Gaussian noise on every observed state entry", low=0.0),
        Option("cost_width", float, 0.5, "width sigma_c of the saturating cost, metres", low=1e-3),
        Option("cost_link_length", float, 0.6,
               "link length the cost measures the tip with (0.6: true links; 1.0: the reference code)", low=0.05),
        Option("substeps", int, 20, "RK4 sub-steps per control period (accuracy vs speed)", low=1),
        Option("success_rule", str, "consecutive", "tip within 12 cm for 10 consecutive steps anywhere, or in the final 10",
               choices=SUCCESS_RULES),
    )

    dt = 0.05
    force_limit = 20.0
    success_radius = 0.12
    success_steps = 10

    def __init__(self, **options) -> None:
        super().__init__(**options)
        self.params = DoublePendulumParams()
        #: ``f(z, u) -> dz/dt`` with this task's physical parameters.
        self.rhs = double_pendulum_rhs(self.params)
        #: the env's integrator: :func:`double_pendulum_stepper`, the same steps as ``rk4_zoh(self.rhs, ...)``.
        self.stepper = double_pendulum_stepper(self.params)
        self._spec = self._build_spec()

    def _build_spec(self) -> TaskSpec:
        cl = self.options["cost_link_length"]
        # features a = [x, xd, th1d, th2d, th1, th2, sin th1, sin th2, cos th1, cos th2]
        linear_map = np.zeros((2, 10))
        linear_map[0, [0, 6, 7]] = [1.0, -cl, -cl]
        linear_map[1, [8, 9]] = [cl, cl]
        cost = SaturatingCost(
            angle_map=np.eye(6)[4:6],
            linear_map=linear_map,
            target=np.array([0.0, 2.0 * cl]),
            width=self.options["cost_width"],
        )
        return TaskSpec(
            name=self.name,
            state_names=("x [m]", "xdot [m/s]", "theta1dot [rad/s]", "theta2dot [rad/s]", "theta1 [rad]", "theta2 [rad]"),
            action_names=("force [N]",),
            dt=self.dt,
            horizon=self.options["horizon"],
            action_low=np.array([-self.force_limit]),
            action_high=np.array([self.force_limit]),
            init_mean=np.array([0.0, 0.0, 0.0, 0.0, math.pi, math.pi]),
            init_cov=np.diag(np.array([0.1, 0.1, 0.1, 0.1, 0.01, 0.01]) ** 2),
            angle_indices=(4, 5),
            cost=cost,
            measurement_noise_std=np.full(6, self.options["measurement_noise"]),
            options=dict(self.options),
        )

    def tip_distance(self, states: np.ndarray) -> np.ndarray:
        """True distance (m) of the second link's tip from the upright target; ``(..., 6)`` -> ``(...)``."""
        l2, l3 = self.params.link1_length, self.params.link2_length
        tip = link_tip(states, l2, l3)
        return np.hypot(tip[..., 0], tip[..., 1] - (l2 + l3))

    def goal_distance(self, state: np.ndarray) -> float:
        return float(self.tip_distance(np.asarray(state)))

    def success(self, episode: Episode) -> bool:
        if episode.terminated:
            return False
        return held_within(self.tip_distance(episode.states), self.success_radius, self.success_steps, self.options["success_rule"])

    def draw(self, state: np.ndarray) -> np.ndarray:
        """RGB image: track, cart, both links and the target marker."""
        l2, l3 = self.params.link1_length, self.params.link2_length
        x, th1, th2 = float(state[0]), float(state[4]), float(state[5])
        reach = l2 + l3
        half = max(2.4, abs(x) + reach + 0.3)
        canvas = Canvas((-half, half), (-reach - 0.2, reach + 0.3), width=480)
        canvas.segment((-half, -0.06), (half, -0.06), 0.01, (120, 120, 120))
        canvas.disc(0.0, reach, 0.03, (230, 60, 60))
        canvas.rectangle(x, 0.0, 0.15, 0.05, (40, 40, 40))
        joint = (x - l2 * math.sin(th1), l2 * math.cos(th1))
        tip = (joint[0] - l3 * math.sin(th2), joint[1] + l3 * math.cos(th2))
        canvas.segment((x, 0.0), joint, 0.03, (200, 140, 40))
        canvas.segment(joint, tip, 0.03, (60, 150, 90))
        canvas.disc(x, 0.0, 0.02, (90, 90, 200))
        canvas.disc(joint[0], joint[1], 0.02, (90, 90, 200))
        return canvas.image


def make_gym_env(render_mode: str | None = None, **options) -> OdeEnv:
    """Entry point of ``gymnasium.make("harness/CartDoublePendulumSwingUp-v0", **options)``."""
    return CartDoublePendulum(**options).make_env(render_mode=render_mode)
