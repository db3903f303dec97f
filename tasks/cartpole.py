"""Cart-pole swing-up as in the PILCO reference implementation V0.9 (``scenarios/cartPole``).

State ``x = [x, xdot, thetadot, theta]`` (m, m/s, rad/s, rad), ``theta = 0`` with the pole
hanging down, one control: the horizontal force on the cart (N). A uniform pole of length ``l``
and mass ``m`` is hinged at the cart (mass ``M``); the cart feels viscous friction ``b xdot``:

    xddot     = [2 m l thd^2 sin th + 3 m g sin th cos th + 4 f - 4 b xd] / [4 (M + m) - 3 m cos^2 th]
    thetaddot = [-3 m l thd^2 sin th cos th - 6 (M + m) g sin th - 6 (f - b xd) cos th]
                / [4 l (M + m) - 3 m l cos^2 th]

(Deisenroth's thesis, App. C; ``tests/tasks/test_cartpole.py`` re-derives them from a sympy
Lagrangian.) The pole tip is at ``(x + l sin th, -l cos th)``; the goal is the tip at ``(0, l)``.
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
class CartPoleParams:
    """Physical parameters (SI units); defaults are ``dynamics_cp.m`` of V0.9."""

    cart_mass: float = 0.5  # M, kg
    pole_mass: float = 0.5  # m, kg
    pole_length: float = 0.5  # l, m
    friction: float = 0.1  # b, N/(m/s)
    gravity: float = 9.82  # g, m/s^2


def cartpole_accelerations(params: CartPoleParams) -> Callable[[float, float, float, float], tuple[float, float]]:
    """``accel(xdot, thetadot, theta, f) -> (xddot, thetaddot)``: the two equations of the module docstring.

    Units: m/s, rad/s, rad, N in; m/s^2, rad/s^2 out. Returns a closure over the parameters
    (constants folded once: the env calls it 160 times per control step).
    """
    big_m, m, l, b, g = params.cart_mass, params.pole_mass, params.pole_length, params.friction, params.gravity
    k_den, k_cos2 = 4.0 * (big_m + m), 3.0 * m
    k_x_w2, k_x_g = 2.0 * m * l, 3.0 * m * g
    k_t_w2, k_t_g = -3.0 * m * l, -6.0 * (big_m + m) * g
    sin, cos = math.sin, math.cos

    def accel(xd: float, thd: float, th: float, f: float) -> tuple[float, float]:
        s, c = sin(th), cos(th)
        den = k_den - k_cos2 * c * c  # 4 (M + m) - 3 m cos^2 th
        fb = f - b * xd
        thd2s = thd * thd * s
        return (
            (k_x_w2 * thd2s + k_x_g * s * c + 4.0 * fb) / den,
            (k_t_w2 * thd2s * c + k_t_g * s - 6.0 * fb * c) / (l * den),
        )

    return accel


def cartpole_rhs(params: CartPoleParams) -> RightHandSide:
    """The right-hand side ``f(z, u) -> dz/dt`` for ``z = [x, xdot, thetadot, theta]``, force ``u = [f]`` (N)."""
    accel = cartpole_accelerations(params)

    def rhs(z: Sequence[float], u: Sequence[float]) -> tuple[float, float, float, float]:
        _, xd, thd, th = z
        xdd, thdd = accel(xd, thd, th, u[0])
        return (xd, xdd, thdd, thd)

    return rhs


def cartpole_stepper(params: CartPoleParams) -> Stepper:
    """``step(z, u, dt, substeps)``: ``rk4_zoh(cartpole_rhs(params), z, u, dt, substeps)`` on scalars.

    The same arithmetic as :func:`tasks.simulation.rk4_zoh` (bit-identical results): the RK4
    stage derivatives of ``x`` and ``theta`` are the stage velocities ``xd_i``, ``thd_i``, and the
    accelerations do not depend on ``x``, so only :func:`cartpole_accelerations` is called.
    ``z``: 4 floats ``[x, xdot, thetadot, theta]``; ``u``: ``[f]`` (N); ``dt`` in s. Returns 4 floats.
    """
    accel = cartpole_accelerations(params)

    def step(z: Sequence[float], u: Sequence[float], dt: float, substeps: int) -> list[float]:
        x, xd, thd, th = map(float, z)
        f = float(u[0])
        h = dt / substeps
        half, sixth = 0.5 * h, h / 6.0
        for _ in range(substeps):
            a1, b1 = accel(xd, thd, th, f)  # k1 = (xd, a1, b1, thd)
            xd2, thd2 = xd + half * a1, thd + half * b1
            a2, b2 = accel(xd2, thd2, th + half * thd, f)  # k2 = (xd2, a2, b2, thd2)
            xd3, thd3 = xd + half * a2, thd + half * b2
            a3, b3 = accel(xd3, thd3, th + half * thd2, f)  # k3 = (xd3, a3, b3, thd3)
            xd4, thd4 = xd + h * a3, thd + h * b3
            a4, b4 = accel(xd4, thd4, th + h * thd3, f)  # k4 = (xd4, a4, b4, thd4)
            x, xd, thd, th = (
                x + sixth * (xd + 2.0 * (xd2 + xd3) + xd4),
                xd + sixth * (a1 + 2.0 * (a2 + a3) + a4),
                thd + sixth * (b1 + 2.0 * (b2 + b3) + b4),
                th + sixth * (thd + 2.0 * (thd2 + thd3) + thd4),
            )
        return [x, xd, thd, th]

    return step


def cartpole_energy(z: Sequence[float], p: CartPoleParams) -> float:
    """Total mechanical energy (J), zero potential at the pivot height.

    ``(M+m) xd^2/2 + m l^2 thd^2/6 + m l (xd thd - g) cos th / 2`` (``dynamics_cp.m``, 2 args).
    """
    _, xd, thd, th = z
    big_m, m, l, g = p.cart_mass, p.pole_mass, p.pole_length, p.gravity
    return (big_m + m) * xd**2 / 2 + m * l**2 * thd**2 / 6 + m * l * (xd * thd - g) * math.cos(th) / 2


def pole_tip(states: np.ndarray, pole_length: float) -> np.ndarray:
    """Pole-tip position ``(x + l sin th, -l cos th)``; ``(..., 4)`` -> ``(..., 2)`` metres."""
    states = np.asarray(states, dtype=np.float64)
    th = states[..., 3]
    return np.stack([states[..., 0] + pole_length * np.sin(th), -pole_length * np.cos(th)], axis=-1)


class CartPole(OdeTask):
    """Cart-pole swing-up (PILCO V0.9 defaults: l = 0.5 m, dt = 0.1 s, 40 steps, |f| <= 10 N).

    Start ``N(0, 0.1^2 I)`` (hanging down); observations carry ``N(0, 0.01^2)`` noise; cost
    ``1 - exp(-d^2 / (2 * 0.25^2))`` with ``d`` the pole tip's distance to ``(0, l)``.

    Success (Kamthe & Deisenroth 2018): the TRUE pole tip (``episode.states``) is within 8 cm of
    the upright target ``(0, l)`` for 10 consecutive recorded states (1 s at dt = 0.1 s) and the
    episode was not terminated; ``success_rule=final`` asks for the last 10 states instead
    (:mod:`tasks.success`).
    """

    name = "cartpole"
    description = "Cart-pole swing-up, PILCO reference implementation V0.9 (l=0.5 m, dt=0.1 s, 4 s)"
    options = (
        Option("pole_length", float, 0.5, "pole length l in metres (0.6: the paper-era variant)", low=0.05, high=5.0),
        Option("horizon", int, 40, "control steps per episode (dt = 0.1 s)", low=10),
        Option("measurement_noise", float, 0.01, "std of the Gaussian noise on every observed state entry", low=0.0),
        Option("cost_width", float, 0.25, "width sigma_c of the saturating cost, metres", low=1e-3),
        Option("substeps", int, 40, "RK4 sub-steps per control period (accuracy vs speed)", low=1),
        Option("success_rule", str, "consecutive", "tip within 8 cm for 10 consecutive steps anywhere, or in the final 10",
               choices=SUCCESS_RULES),
    )

    dt = 0.1
    force_limit = 10.0
    success_radius = 0.08
    success_steps = 10

    def __init__(self, **options) -> None:
        super().__init__(**options)
        self.params = CartPoleParams(pole_length=self.options["pole_length"])
        #: ``f(z, u) -> dz/dt`` with this task's physical parameters.
        self.rhs = cartpole_rhs(self.params)
        #: the env's integrator: :func:`cartpole_stepper`, the same steps as ``rk4_zoh(self.rhs, ...)``.
        self.stepper = cartpole_stepper(self.params)
        self._spec = self._build_spec()

    def _build_spec(self) -> TaskSpec:
        l = self.params.pole_length
        # features a = [x, xd, thd, th, sin th, cos th]; residual = tip - (0, l)
        cost = SaturatingCost(
            angle_map=np.array([[0.0, 0.0, 0.0, 1.0]]),
            linear_map=np.array([[1.0, 0.0, 0.0, 0.0, l, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, -l]]),
            target=np.array([0.0, l]),
            width=self.options["cost_width"],
        )
        return TaskSpec(
            name=self.name,
            state_names=("x [m]", "xdot [m/s]", "thetadot [rad/s]", "theta [rad]"),
            action_names=("force [N]",),
            dt=self.dt,
            horizon=self.options["horizon"],
            action_low=np.array([-self.force_limit]),
            action_high=np.array([self.force_limit]),
            init_mean=np.zeros(4),
            init_cov=0.1**2 * np.eye(4),
            angle_indices=(3,),
            cost=cost,
            measurement_noise_std=np.full(4, self.options["measurement_noise"]),
            options=dict(self.options),
        )

    def tip_distance(self, states: np.ndarray) -> np.ndarray:
        """True distance (m) of the pole tip from the upright target ``(0, l)``; ``(..., 4)`` -> ``(...)``."""
        tips = pole_tip(states, self.params.pole_length)
        return np.hypot(tips[..., 0], tips[..., 1] - self.params.pole_length)

    def goal_distance(self, state: np.ndarray) -> float:
        return float(self.tip_distance(np.asarray(state)))

    def success(self, episode: Episode) -> bool:
        if episode.terminated:
            return False
        return held_within(self.tip_distance(episode.states), self.success_radius, self.success_steps, self.options["success_rule"])

    def draw(self, state: np.ndarray) -> np.ndarray:
        """RGB image of the cart-pole: track, cart, pole and the target marker."""
        l = self.params.pole_length
        x, th = float(state[0]), float(state[3])
        half = max(2.4, abs(x) + l + 0.3)
        canvas = Canvas((-half, half), (-1.5 * l - 0.2, 1.5 * l + 0.2), width=480)
        canvas.segment((-half, -0.06), (half, -0.06), 0.01, (120, 120, 120))
        canvas.disc(0.0, l, 0.03, (230, 60, 60))
        canvas.rectangle(x, 0.0, 0.15, 0.05, (40, 40, 40))
        tip = (x + l * math.sin(th), -l * math.cos(th))
        canvas.segment((x, 0.0), tip, 0.03, (200, 140, 40))
        canvas.disc(x, 0.0, 0.02, (90, 90, 200))
        return canvas.image


def make_gym_env(render_mode: str | None = None, **options) -> OdeEnv:
    """Entry point of ``gymnasium.make("harness/CartPoleSwingUp-v0", **options)``."""
    return CartPole(**options).make_env(render_mode=render_mode)
