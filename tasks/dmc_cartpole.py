"""dm_control suite ``cartpole``/``swingup`` as a harness task (pip extra ``dmc``).

The system is DeepMind's MuJoCo cart-pole (``dm_control/suite/cartpole.xml``: cart 1 kg on a
slider, pole a 1 m capsule of 0.1 kg hinged on the cart, physics step 0.01 s with RK4, motor gear
10 so the action ``a in [-1, 1]`` is a force of ``10 a`` N). The harness environment repeats each
action for ``action_repeat`` physics steps (default 10, so ``dt = 0.1`` s) and runs ``horizon``
control steps (default: 10 s, the suite's time limit).

Observation (5,): ``[x, cos theta, sin theta, xdot, thetadot]`` = the suite's ``position`` and
``velocity`` observations concatenated; ``theta = 0`` is the pole pointing up, so the pole tip
is at ``(x + l sin theta, l cos theta)`` relative to the rail, ``l = 1`` m.

Rewards: ``step`` returns ``-cost(state)`` (the harness contract) with the PILCO-style saturating
cost on the pole tip's distance to the upright target ``(0, l)``; the dm_control suite's own
(smooth) reward, summed over the repeated physics steps, is ``info["dmc_reward"]``, so the
dm_control episode return (at most 1000 for 10 s) can be logged next to the harness's cost.

Stepping: ``step`` sets the control once and calls MuJoCo directly, ``mj_step`` then ``mj_step1``
per physics step on the suite physics' own ``MjModel``/``MjData`` -- exactly what dm_control's
``Environment.step`` does with ``legacy_step`` (the suite default) -- and evaluates the suite
reward with :func:`swingup_reward` on Python floats. This skips dm_control's per-physics-step
Python (named indexing, observation dicts, numpy reward helpers), about 90 % of the step time.
dm_control still builds the model and draws the initial state (``reset``), so seeding is
unchanged; ``tests/tasks/test_dmc_cartpole.py`` checks observations and rewards against
``suite.load("cartpole", "swingup").step`` over 200 random-action steps.

dm_control is imported when an environment is made, never at import time of this module.
"""

from __future__ import annotations

import math
import os
from typing import Any

import gymnasium as gym
import numpy as np

from harness.errors import InteractionError, NumericalError
from harness.options import Option
from harness.task import Episode, SaturatingCost, Task, TaskSpec, check_action

#: physics time step of ``cartpole.xml`` (s).
PHYSICS_TIMESTEP = 0.01
#: pole length of ``cartpole.xml`` (capsule ``fromto="0 0 0 0 0 1"``), metres.
POLE_LENGTH = 1.0
#: force per unit action (actuator gear), N.
GEAR = 10.0
#: std of the suite's swing-up initial perturbations (position, angle and both velocities).
INIT_STD = 0.01
#: seconds of system time in a default episode (the suite's time limit).
EPISODE_SECONDS = 10.0

STATE_NAMES = ("x [m]", "cos theta", "sin theta", "xdot [m/s]", "thetadot [rad/s]")
#: the suite's reward margins: cart position (m), control (action units), pole angular rate (rad/s).
CART_MARGIN, CONTROL_MARGIN, ANGULAR_VELOCITY_MARGIN = 2.0, 1.0, 5.0
#: scale of dm_control's Gaussian tolerance sigmoid, value 0.1 at the margin: ``sqrt(-2 ln 0.1)``.
_GAUSSIAN_SCALE = math.sqrt(-2.0 * math.log(0.1))
#: indices into MuJoCo's ``xmat`` row of a body (row-major 3x3): ``zz`` = cos theta, ``xz`` = sin theta.
_XMAT_ZZ, _XMAT_XZ = 8, 2
#: body index of ``pole_1`` (0 world, 1 cart).
_POLE_BODY = 2


def _gaussian_tolerance(x: float, margin: float) -> float:
    """dm_control's ``rewards.tolerance(x, bounds=(0, 0), margin)``, Gaussian sigmoid, 0.1 at the margin."""
    if x == 0.0:
        return 1.0
    d = abs(x) / margin
    return math.exp(-0.5 * (d * _GAUSSIAN_SCALE) ** 2)


def swingup_reward(cart_position: float, pole_cos: float, control: float, pole_angular_velocity: float) -> float:
    """The suite's smooth swing-up reward of one physics state (``cartpole.Balance._get_reward``), in [0, 1].

    ``upright * small_control * small_velocity * centered`` with ``upright = (cos theta + 1) / 2``,
    ``small_control = (4 + q(u)) / 5`` (``q(u) = 1 - u^2`` for ``|u| < 1``, else 0),
    ``small_velocity = (1 + g(thetadot, 5)) / 2`` and ``centered = (1 + g(x, 2)) / 2``, where
    ``g(v, m) = exp(-(|v| / m)^2 ln 10)`` is dm_control's Gaussian tolerance (0.1 at the margin ``m``).
    Arguments: cart position (m), ``cos theta``, control ``u`` (action units), pole rate (rad/s).
    """
    upright = (pole_cos + 1.0) / 2.0
    centered = (1.0 + _gaussian_tolerance(cart_position, CART_MARGIN)) / 2.0
    scaled_control = abs(control) / CONTROL_MARGIN
    small_control = (4.0 + (1.0 - scaled_control**2 if scaled_control < 1.0 else 0.0)) / 5.0
    small_velocity = (1.0 + _gaussian_tolerance(pole_angular_velocity, ANGULAR_VELOCITY_MARGIN)) / 2.0
    return upright * small_control * small_velocity * centered


def swingup_observation_moments(std: float = INIT_STD) -> tuple[np.ndarray, np.ndarray]:
    """Exact mean ``(5,)`` and covariance ``(5, 5)`` of the suite's swing-up start in observation coordinates.

    The suite draws ``x, xdot, thetadot ~ N(0, std^2)`` and ``theta = pi + e``, ``e ~ N(0, std^2)``,
    independently. So ``cos theta = -cos e`` and ``sin theta = -sin e`` with
    ``E[cos e] = exp(-s^2/2)``, ``Var[cos e] = (1 + exp(-2 s^2))/2 - exp(-s^2)``,
    ``E[sin e] = 0``, ``Var[sin e] = (1 - exp(-2 s^2))/2`` and ``Cov[cos e, sin e] = 0`` (odd in ``e``).
    """
    s2 = std * std
    mean = np.array([0.0, -math.exp(-s2 / 2), 0.0, 0.0, 0.0])
    var_cos = (1 + math.exp(-2 * s2)) / 2 - math.exp(-s2)
    var_sin = (1 - math.exp(-2 * s2)) / 2
    return mean, np.diag([s2, var_cos, var_sin, s2, s2])


def pole_tip(states: np.ndarray, pole_length: float = POLE_LENGTH) -> np.ndarray:
    """Pole-tip position ``(x + l sin theta, l cos theta)``; ``(..., 5) -> (..., 2)`` metres."""
    states = np.asarray(states, dtype=np.float64)
    return np.stack([states[..., 0] + pole_length * states[..., 2], pole_length * states[..., 1]], axis=-1)


def tip_cost(width: float, pole_length: float = POLE_LENGTH) -> SaturatingCost:
    """``1 - exp(-d^2 / (2 width^2))``, ``d`` = distance of the pole tip to ``(0, l)``.

    Linear in the observation (which already holds ``cos theta, sin theta``), so no angle features.
    """
    l = pole_length
    return SaturatingCost(
        angle_map=np.zeros((0, 5)),
        linear_map=np.array([[1.0, 0.0, l, 0.0, 0.0], [0.0, l, 0.0, 0.0, 0.0]]),
        target=np.array([0.0, l]),
        width=width,
    )


class DMCCartpoleEnv(gym.Env):
    """Gymnasium environment around ``suite.load("cartpole", "swingup")`` with action repeat.

    ``reset(seed=s)`` seeds both the suite task's ``RandomState`` (initial state) and the
    measurement noise. ``reset(options={"state": x0})`` starts from a given observation-coordinate
    state ``x0`` instead. ``info`` carries ``"state"`` (true observation), ``"action_clipped"`` and
    (after ``step``) ``"dmc_reward"``, the suite reward summed over the ``action_repeat`` physics
    steps. The suite's own time limit is switched off; the episode is truncated after
    ``spec.horizon`` steps and never terminated (swing-up has no failure states).
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        spec: TaskSpec,
        action_repeat: int,
        render_mode: str | None = None,
        measurement_noise: bool = True,
        render_size: tuple[int, int] = (240, 320),
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"{spec.name}: render_mode must be None or 'rgb_array', got {render_mode!r}")
        os.environ.setdefault("MUJOCO_GL", "egl")
        from dm_control import suite

        self.spec_ = spec
        self.action_repeat = int(action_repeat)
        self.render_mode = render_mode
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": max(1, int(round(1.0 / spec.dt)))}
        self._render_size = render_size
        self._noise = measurement_noise and bool(np.any(spec.measurement_noise_std > 0))
        self._dm_random = np.random.RandomState()
        self._dm_env = suite.load(
            "cartpole", "swingup", task_kwargs={"random": self._dm_random, "time_limit": float("inf")}
        )
        self.physics = self._dm_env.physics
        import mujoco

        self._mj_step, self._mj_step1 = mujoco.mj_step, mujoco.mj_step1
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(5,), dtype=np.float64)
        self.action_space = gym.spaces.Box(spec.action_low, spec.action_high, dtype=np.float64)
        self._state: np.ndarray | None = None
        self._t = 0
        self._done = True

    @property
    def task_spec(self) -> TaskSpec:
        """The task's spec (``env.spec`` is gymnasium's registration spec)."""
        return self.spec_

    @staticmethod
    def _flatten(observation: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([observation["position"], observation["velocity"]]).astype(np.float64)

    def _observe(self, state: np.ndarray) -> np.ndarray:
        if not self._noise:
            return state.copy()
        return state + self.spec_.measurement_noise_std * self.np_random.standard_normal(5)

    def rng_state(self) -> dict[str, Any]:
        """Both random streams (observation noise and dm_control's task RNG), for checkpoints."""
        return {"np_random": self.np_random.bit_generator.state, "dm_random": self._dm_random.get_state()}

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self.np_random.bit_generator.state = state["np_random"]
        self._dm_random.set_state(state["dm_random"])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._dm_random.seed(seed)
        time_step = self._dm_env.reset()
        if options and options.get("state") is not None:
            x0 = np.asarray(options["state"], dtype=np.float64).reshape(-1)
            if x0.shape != (5,) or not np.all(np.isfinite(x0)):
                raise ValueError(f"{self.spec_.name}: reset state must be finite with shape (5,)")
            with self.physics.reset_context():
                self.physics.named.data.qpos["slider"] = x0[0]
                self.physics.named.data.qpos["hinge_1"] = math.atan2(x0[2], x0[1])
                self.physics.named.data.qvel["slider"] = x0[3]
                self.physics.named.data.qvel["hinge_1"] = x0[4]
            state = self._flatten(self._dm_env.task.get_observation(self.physics))
        else:
            state = self._flatten(time_step.observation)
        self._state, self._t, self._done = state, 0, False
        return self._observe(state), {"state": state.copy()}

    def step(self, action):
        spec = self.spec_
        if self._done:
            raise InteractionError(
                f"{spec.name}: step() called {'before reset()' if self._state is None else 'after the episode ended'}; "
                "call reset() first"
            )
        u, clipped = check_action(action, spec)
        model, data = self.physics.model.ptr, self.physics.data.ptr  # mujoco.MjModel, mujoco.MjData
        warnings_before = data.warning.number.copy()
        data.ctrl[:] = u  # held for all action_repeat physics steps (dm_control's before_step)
        control = float(data.ctrl[0])
        qpos, qvel, pole_xmat = data.qpos, data.qvel, data.xmat[_POLE_BODY]
        dmc_reward = 0.0
        for _ in range(self.action_repeat):
            self._mj_step(model, data)  # RK4 physics step of 0.01 s
            self._mj_step1(model, data)  # positions/velocities-dependent fields (xmat) of the new state
            dmc_reward += swingup_reward(float(qpos[0]), float(pole_xmat[_XMAT_ZZ]), control, float(qvel[1]))
        state = np.array([qpos[0], pole_xmat[_XMAT_ZZ], pole_xmat[_XMAT_XZ], qvel[0], qvel[1]])
        if not np.all(np.isfinite(state)) or np.any(data.warning.number > warnings_before):
            self._done = True
            raise NumericalError(f"{spec.name}: MuJoCo produced an invalid state at step {self._t}")
        self._state = state
        self._t += 1
        truncated = self._t >= spec.horizon
        self._done = truncated
        reward = -float(spec.cost(state))
        info = {"state": state.copy(), "action_clipped": clipped, "dmc_reward": dmc_reward}
        return self._observe(state), reward, False, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        height, width = self._render_size
        return self.physics.render(height=height, width=width, camera_id=0)

    def close(self) -> None:
        self._dm_env.close()


class DMCCartpole(Task):
    """dm_control cartpole swing-up (``suite.load("cartpole", "swingup")``) with action repeat.

    State ``[x, cos theta, sin theta, xdot, thetadot]``; action ``a in [-1, 1]`` (force ``10 a`` N);
    ``dt = action_repeat * 0.01`` s (0.1 s by default); horizon 10 s (100 steps by default).
    Start: the suite's swing-up distribution (pole down, all perturbations ``0.01 N(0, 1)``), as
    exact moments in :func:`swingup_observation_moments`. Cost: :func:`tip_cost` (width 0.25 m).
    ``spec.angle_indices`` is empty: the observation already holds ``cos theta, sin theta``.

    Success: in each of the last ``round(1 / dt)`` recorded true states (the final second;
    10 states at dt = 0.1) the cart is centred, ``|x| <= 0.25`` m, and the pole upright,
    ``cos theta >= 0.995`` (the suite's sparse-reward region); the episode must have at least
    that many steps.
    """

    name = "dmc-cartpole"
    description = "dm_control suite cartpole swingup (MuJoCo), action repeat 10 (dt=0.1 s), 10 s"
    extra = "dmc"
    requires = ("dm_control",)
    options = (
        Option("action_repeat", int, 10, "physics steps of 0.01 s per control step (dt = 0.01 * action_repeat)",
               low=1, high=100),
        Option("horizon", int, None, "control steps per episode; default: 10 s of system time", low=1),
        Option("cost_width", float, 0.25, "width sigma_c of the saturating pole-tip cost, metres", low=1e-3),
        Option("measurement_noise", float, 0.0, "std of the Gaussian noise on every observed entry", low=0.0),
    )

    action_limit = 1.0
    cart_range = 0.25
    min_cos = 0.995

    def __init__(self, **options) -> None:
        super().__init__(**options)
        self.action_repeat = self.options["action_repeat"]
        self.dt = self.action_repeat * PHYSICS_TIMESTEP
        horizon = self.options["horizon"]
        if horizon is None:
            horizon = max(1, round(EPISODE_SECONDS / self.dt))
            self.options["horizon"] = horizon  # record the resolved value with the run
        mean, cov = swingup_observation_moments()
        self._spec = TaskSpec(
            name=self.name,
            state_names=STATE_NAMES,
            action_names=(f"a (force = {GEAR:g} a N)",),
            dt=self.dt,
            horizon=horizon,
            action_low=np.array([-self.action_limit]),
            action_high=np.array([self.action_limit]),
            init_mean=mean,
            init_cov=cov,
            angle_indices=(),
            cost=tip_cost(self.options["cost_width"]),
            measurement_noise_std=np.full(5, self.options["measurement_noise"]),
            options=dict(self.options),
        )

    @property
    def spec(self) -> TaskSpec:
        return self._spec

    def make_env(self, render_mode: str | None = None, measurement_noise: bool = True) -> DMCCartpoleEnv:
        return DMCCartpoleEnv(self._spec, self.action_repeat, render_mode=render_mode,
                              measurement_noise=measurement_noise)

    @property
    def success_steps(self) -> int:
        """Number of final states that must be in the target region: one second's worth."""
        return max(1, round(1.0 / self.dt))

    def goal_distance(self, state: np.ndarray) -> float:
        """Distance (m) of the pole tip from the upright target ``(0, POLE_LENGTH)``."""
        tip = pole_tip(np.asarray(state, dtype=np.float64))
        return float(np.hypot(tip[0], tip[1] - POLE_LENGTH))

    def success(self, episode: Episode) -> bool:
        n = self.success_steps
        if episode.terminated or episode.steps < n:
            return False
        final = np.asarray(episode.states)[-n:]
        return bool(np.all(np.abs(final[:, 0]) <= self.cart_range) and np.all(final[:, 1] >= self.min_cos))


def make_gym_env(render_mode: str | None = None, **options) -> DMCCartpoleEnv:
    """Entry point of ``gymnasium.make("harness/DMCCartpoleSwingup-v0", **options)``."""
    return DMCCartpole(**options).make_env(render_mode=render_mode)
