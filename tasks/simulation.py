"""The one integration path of all simulated tasks, and the gymnasium environment around it.

Integration
-----------
:func:`rk4_zoh` advances ``dz/dt = f(z, u)`` over one control period ``dt`` with the control held
constant (zero-order hold, as ``plant.ctrl = @zoh`` in the reference implementation) using
``substeps`` classical fourth-order Runge-Kutta steps of length ``dt / substeps``. The right-hand
side works on plain Python floats (sequences in, tuple out): on 4-12 dimensional states, numpy's
per-call overhead would cost more than the arithmetic.

The reference implementation integrates with ``ode45`` at ``RelTol = AbsTol = 1e-12``;
:func:`reference_step` is that integration here (``solve_ivp``, DOP853, ``rtol = atol = 1e-12``).
One-step error of :func:`rk4_zoh` against it (max-abs over the state after one control period,
worst of 100 states per set, control at a random bound; sets: *start* = the task's initial
distribution, *target* = the same spread around the upright target, *box* = uniform with angular
rates up to 10 rad/s and any angles; ``tests/tasks/test_simulation.py`` re-measures them):

================  ======  ==========  =======  =======  =======
task              dt [s]  substeps    start    target   box
================  ======  ==========  =======  =======  =======
cart-pole         0.10    40 default  9.3e-9   1.2e-8   9.6e-8
cart-pole         0.10    50          3.8e-9   4.9e-9   4.0e-8
double pendulum   0.05    20 default  3.1e-8   6.7e-8   2.2e-5
double pendulum   0.05    40          1.9e-9   4.2e-9   1.5e-6
================  ======  ==========  =======  =======  =======

Accuracy against speed: RK4 needs 4 right-hand-side evaluations per sub-step, ~0.6 us (cart-pole)
and ~1.1 us (double pendulum) each in CPython with the fused steppers below. The defaults use the
same RK4 step ``h = 2.5 ms`` for both tasks: errors of 1e-8 to 1e-7 near the start and the target,
up to 2e-5 at angular rates of 10 rad/s (more beyond: the error grows roughly with the fourth
power of the rates), i.e. three or more orders of magnitude below the 0.01 measurement noise, at
~11,000 (cart-pole) and ~8,600 (double pendulum) env steps per CPU second, above the 5,000 the RL
baselines need. The option ``substeps`` (recorded with every run) buys the 1e-8 of the
reference's ``ode45`` (cart-pole 50, double pendulum 40) at ~9,700 and ~5,000 steps per CPU
second (``benchmarks/bench_env_steps.py``, ``results/benchmarks/env_steps.md``).

Fused steppers: a task may hand :class:`OdeEnv` a *stepper*, ``step(z, u, dt, substeps)``, that
performs exactly the arithmetic of ``rk4_zoh(rhs, z, u, dt, substeps)`` on local scalars: the
stages of a mechanical system's angles and positions are its stage velocities, so only the
accelerations need a function call, and no per-stage lists are built. The results are
bit-identical to :func:`rk4_zoh` (``tests/tasks/test_simulation.py``; the seeded rollouts of
``tests/tasks/test_env_trajectories.py`` equal those recorded with the generic path) at 1.4-2x
the speed.

Environment
-----------
:class:`OdeEnv` is the generic gymnasium environment of ODE tasks. It implements the contract of
:mod:`harness.task`: the true state starts from ``N(init_mean, init_cov)``, the observation is the
true state plus Gaussian measurement noise (``spec.measurement_noise_std``; switch off with
``measurement_noise=False``), the reward is ``-spec.cost(true next state)``, ``truncated`` after
``spec.horizon`` steps, ``terminated`` when the task's ``left_region`` predicate says so, and
``info = {"state": true state, "action_clipped": bool}``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np

from harness.errors import InteractionError, NumericalError
from harness.task import Task, TaskSpec, check_action

#: ``f(z, u) -> dz/dt``: state and control as float sequences, derivative as a tuple of floats.
RightHandSide = Callable[[Sequence[float], Sequence[float]], Sequence[float]]
#: ``step(z, u, dt, substeps) -> z_next``: one control period, the signature of ``rk4_zoh`` without ``rhs``.
Stepper = Callable[[Sequence[float], Sequence[float], float, int], list[float]]


def rk4_zoh(rhs: RightHandSide, z: Sequence[float], u: Sequence[float], dt: float, substeps: int) -> list[float]:
    """Advance ``z`` by ``dt`` seconds with control ``u`` held constant.

    Args:
        rhs: ``f(z, u)``, the time-invariant right-hand side.
        z: state, length ``n`` (floats).
        u: control, length ``F`` (floats), constant over the step.
        dt: control period, seconds.
        substeps: number of classical RK4 steps of length ``dt / substeps``.

    Returns:
        The state after ``dt`` seconds as a list of ``n`` floats.
    """
    h = dt / substeps
    half = 0.5 * h
    sixth = h / 6.0
    z = [float(v) for v in z]
    for _ in range(substeps):
        k1 = rhs(z, u)
        k2 = rhs([a + half * b for a, b in zip(z, k1)], u)
        k3 = rhs([a + half * b for a, b in zip(z, k2)], u)
        k4 = rhs([a + h * b for a, b in zip(z, k3)], u)
        z = [a + sixth * (b1 + 2.0 * (b2 + b3) + b4) for a, b1, b2, b3, b4 in zip(z, k1, k2, k3, k4)]
    return z


def reference_step(rhs: RightHandSide, z: Sequence[float], u: Sequence[float], dt: float, tol: float = 1e-12) -> np.ndarray:
    """The same step as :func:`rk4_zoh` by ``scipy.integrate.solve_ivp`` (DOP853, ``rtol = atol = tol``).

    For accuracy checks only (about a thousand times slower than :func:`rk4_zoh`).
    """
    from scipy.integrate import solve_ivp

    u = [float(v) for v in u]
    sol = solve_ivp(
        lambda t, y: rhs(y.tolist(), u), (0.0, dt), np.asarray(z, dtype=np.float64),
        method="DOP853", rtol=tol, atol=tol,
    )
    if not sol.success:
        raise NumericalError(f"reference integration failed: {sol.message}")
    return sol.y[:, -1]


Drawer = Callable[[np.ndarray], np.ndarray]


class OdeEnv(gym.Env):
    """Gymnasium environment of a task whose system is an ODE, stepped with :func:`rk4_zoh`.

    Args:
        spec: the task's :class:`~harness.task.TaskSpec` (bounds, horizon, cost, noise, initial
            distribution).
        rhs: ``f(z, u)`` on the *physical* state.
        substeps: RK4 sub-steps per control period.
        stepper: a fused equivalent of ``rk4_zoh(rhs, ...)`` (same results, faster); ``None``:
            :func:`rk4_zoh` on ``rhs``.
        left_region: ``pred(state) -> bool``, true when the system left its allowed region
            (the episode then ends with ``terminated = True``); ``None``: never.
        draw: ``draw(state) -> (H, W, 3) uint8`` image, used by ``render_mode="rgb_array"``.
        render_mode: ``None`` or ``"rgb_array"``.
        measurement_noise: add ``N(0, diag(spec.measurement_noise_std^2))`` to observations.
        physical_from_state, state_from_physical: maps between the task state ``x`` (shape
            ``(D,)``, what the cost, the observation and ``info["state"]`` use) and the integrated
            physical state; identity when ``None`` (``spec.physical_state_dim`` is ``None``).

    Reset options: ``{"state": x0}`` starts from the given true state instead of sampling it.
    After the episode ended (terminated or truncated) ``step`` raises
    :class:`~harness.errors.InteractionError` until the next ``reset``.
    """

    def __init__(
        self,
        spec: TaskSpec,
        rhs: RightHandSide,
        substeps: int,
        *,
        left_region: Callable[[np.ndarray], bool] | None = None,
        draw: Drawer | None = None,
        render_mode: str | None = None,
        measurement_noise: bool = True,
        physical_from_state: Callable[[np.ndarray], Sequence[float]] | None = None,
        state_from_physical: Callable[[Sequence[float]], np.ndarray] | None = None,
        stepper: Stepper | None = None,
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"{spec.name}: render_mode must be None or 'rgb_array', got {render_mode!r}")
        if render_mode is not None and draw is None:
            raise ValueError(f"{spec.name}: no drawing function for render_mode {render_mode!r}")
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        self.spec_ = spec
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": max(1, int(round(1.0 / spec.dt)))}
        self.render_mode = render_mode
        self._rhs = rhs
        self._stepper = stepper if stepper is not None else partial(rk4_zoh, rhs)
        self._substeps = int(substeps)
        self._left_region = left_region
        self._draw = draw
        self._noise = measurement_noise
        self._noise_std = spec.measurement_noise_std.copy()
        self._chol0 = _cholesky_psd(spec.init_cov)
        self._to_physical = physical_from_state
        self._from_physical = state_from_physical
        d = spec.state_dim
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(d,), dtype=np.float64)
        self.action_space = gym.spaces.Box(spec.action_low, spec.action_high, dtype=np.float64)
        self._z: list[float] | None = None
        self._state: np.ndarray | None = None
        self._t = 0
        self._done = True
        #: number of clipped actions in the current episode.
        self.clipped_actions = 0

    @property
    def task_spec(self) -> TaskSpec:
        """The task's spec (``env.spec`` is gymnasium's registration spec)."""
        return self.spec_

    @property
    def state(self) -> np.ndarray:
        """Current true state ``x``, shape ``(D,)``."""
        if self._state is None:
            raise InteractionError(f"{self.spec_.name}: call reset() before reading the state")
        return self._state.copy()

    def _observe(self, state: np.ndarray) -> np.ndarray:
        if not self._noise:
            return state.copy()
        return state + self._noise_std * self.np_random.standard_normal(state.shape[0])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        spec = self.spec_
        if options and options.get("state") is not None:
            state = np.asarray(options["state"], dtype=np.float64).reshape(-1).copy()
            if state.shape != (spec.state_dim,) or not np.all(np.isfinite(state)):
                raise ValueError(f"{spec.name}: reset state must be finite with shape ({spec.state_dim},)")
        else:
            state = spec.init_mean + self._chol0 @ self.np_random.standard_normal(spec.state_dim)
        self._state = state
        self._z = list(self._to_physical(state)) if self._to_physical else state.tolist()
        self._t = 0
        self._done = False
        self.clipped_actions = 0
        return self._observe(state), {"state": state.copy()}

    def step(self, action):
        spec = self.spec_
        if self._done:
            raise InteractionError(
                f"{spec.name}: step() called {'before reset()' if self._z is None else 'after the episode ended'}; "
                "call reset() first"
            )
        u, clipped = check_action(action, spec)
        try:
            z = self._stepper(self._z, u.tolist(), spec.dt, self._substeps)
        except (OverflowError, ValueError, ZeroDivisionError) as exc:
            z = [math.nan]
            cause: Exception | None = exc
        else:
            cause = None
        if not all(map(math.isfinite, z)):
            self._done = True
            raise NumericalError(
                f"{spec.name}: the simulation diverged at step {self._t} (non-finite state); "
                "the state or the control is far outside the task's range"
            ) from cause
        state = self._from_physical(z) if self._from_physical else np.array(z)
        self._z, self._state = z, state
        self._t += 1
        self.clipped_actions += int(clipped)
        reward = -float(spec.cost(state))
        terminated = bool(self._left_region(state)) if self._left_region else False
        truncated = self._t >= spec.horizon
        self._done = terminated or truncated
        return self._observe(state), reward, terminated, truncated, {"state": state.copy(), "action_clipped": clipped}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._state is None:
            raise InteractionError(f"{self.spec_.name}: call reset() before render()")
        return self._draw(self._state)


def _cholesky_psd(cov: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L L^T = cov`` for a symmetric PSD ``cov`` (zero variances allowed)."""
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.min(w) < -1e-12 * max(1.0, float(np.max(np.abs(w)))):
        raise ValueError("init_cov is not positive semi-definite")
    return v * np.sqrt(np.clip(w, 0.0, None))


class OdeTask(Task):
    """Base of the simulated tasks: subclasses set ``self._spec`` and ``self.rhs`` (and optionally
    ``self.stepper``, a fused ``rk4_zoh`` of ``rhs``) in ``__init__``, declare a ``substeps`` option
    and a ``draw(state) -> RGB`` method; environments are :class:`OdeEnv` instances integrating
    ``rhs`` with the shared RK4."""

    _spec: TaskSpec
    rhs: RightHandSide
    stepper: Stepper | None = None

    @property
    def spec(self) -> TaskSpec:
        return self._spec

    def make_env(self, render_mode: str | None = None, measurement_noise: bool = True) -> OdeEnv:
        return OdeEnv(
            self._spec,
            self.rhs,
            substeps=self.options["substeps"],
            draw=self.draw,
            render_mode=render_mode,
            measurement_noise=measurement_noise,
            stepper=self.stepper,
        )
