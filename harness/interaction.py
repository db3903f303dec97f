"""Budgeted, counted access to the system: the only way a learner touches a task.

:class:`Interaction` owns the environment. Every ``step`` is counted and converted to seconds of
system time (``steps * dt``); a step beyond the budget raises
:class:`~harness.errors.BudgetExhaustedError` *before* the system moves; every episode is
recorded as an :class:`~harness.task.Episode`. Learners read the counters but cannot change them.

Evaluation episodes run on a separate environment (:mod:`harness.evaluation`) and never pass
through here, so they are never counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import fields
from typing import Any

import gymnasium as gym
import numpy as np

from harness.errors import BudgetExhaustedError, InteractionError
from harness.task import Episode, TaskSpec, check_action
from harness.threads import stepping_threads


class _EpisodeBuffer:
    """Accumulates one episode's arrays."""

    def __init__(self, observation: np.ndarray, state: np.ndarray) -> None:
        self.observations = [observation]
        self.states = [state]
        self.actions: list[np.ndarray] = []
        self.costs: list[float] = []
        self.clipped = 0
        self.terminated = False
        self.extra: dict[str, float] = {}

    def to_episode(self, spec: TaskSpec) -> Episode:
        d, f = spec.state_dim, spec.action_dim
        return Episode(
            observations=np.asarray(self.observations, dtype=np.float64).reshape(-1, d),
            states=np.asarray(self.states, dtype=np.float64).reshape(-1, d),
            actions=np.asarray(self.actions, dtype=np.float64).reshape(-1, f),
            costs=np.asarray(self.costs, dtype=np.float64),
            terminated=self.terminated,
            clipped_actions=self.clipped,
            extra=dict(self.extra),
        )


def run_episode(
    env: gym.Env,
    spec: TaskSpec,
    policy: Callable[[np.ndarray], Any],
    seed: int | None = None,
    max_steps: int | None = None,
) -> Episode:
    """Run one uncounted episode of ``policy`` on ``env`` and return it (evaluation, conformance
    checks; counted episodes go through :meth:`Interaction.rollout`). The episode ends at
    termination, truncation (the task horizon) or after ``max_steps`` steps.
    """
    obs, info = env.reset(seed=seed)
    buffer = _EpisodeBuffer(np.asarray(obs, dtype=np.float64), _state_of(info, obs))
    limit = spec.horizon if max_steps is None else min(int(max_steps), spec.horizon)
    with stepping_threads():
        for _ in range(limit):
            action, _ = check_action(policy(np.asarray(obs, dtype=np.float64)), spec)
            obs, reward, terminated, truncated, info = env.step(action)
            _record(buffer, obs, reward, terminated, info, action)
            if terminated or truncated:
                break
    return buffer.to_episode(spec)


def _state_of(info: dict, obs: Any) -> np.ndarray:
    return np.asarray(info.get("state", obs), dtype=np.float64)


def _record(buffer: _EpisodeBuffer, obs: Any, reward: float, terminated: bool, info: dict, action: np.ndarray) -> None:
    buffer.observations.append(np.asarray(obs, dtype=np.float64))
    buffer.states.append(_state_of(info, obs))
    buffer.actions.append(np.asarray(action, dtype=np.float64))
    buffer.costs.append(-float(reward))
    buffer.clipped += int(bool(info.get("action_clipped", False)))
    buffer.terminated = buffer.terminated or bool(terminated)
    for key in ("dmc_reward",):
        if key in info:
            buffer.extra[key] = buffer.extra.get(key, 0.0) + float(info[key])


class Interaction:
    """Counted, budgeted access to one environment instance.

    Args:
        env: the environment (owned from now on by this object).
        spec: the task spec (``dt``, horizon, action bounds).
        budget_seconds: seconds of system time the learner may consume; ``None`` = unlimited.
        seed: seed of the first ``reset``; later resets continue the environment's RNG.

    Attributes (read-only for learners): ``steps``, ``seconds``, ``episodes`` (completed
    :class:`Episode` objects, in order), ``budget_seconds``, ``remaining_steps``.
    """

    def __init__(self, env: gym.Env, spec: TaskSpec, budget_seconds: float | None = None, seed: int = 0) -> None:
        if budget_seconds is not None and not (budget_seconds > 0 and math.isfinite(budget_seconds)):
            raise ValueError(f"budget_seconds must be a positive number, got {budget_seconds!r}")
        self._env = env
        self._spec = spec
        self._budget_steps = None if budget_seconds is None else int(math.floor(budget_seconds / spec.dt + 1e-9))
        self._steps = 0
        self._episodes: list[Episode] = []
        self._current: _EpisodeBuffer | None = None
        self._last_obs: np.ndarray | None = None
        self._seed: int | None = int(seed)
        self._on_episode: list[Callable[[Episode], None]] = []
        #: how the running episode was started (the seed and the env's RNG before its reset), kept so
        #: that a checkpoint taken before its first step can start it again exactly
        self._started_from: dict[str, Any] | None = None

    # -- counters -------------------------------------------------------------------------
    @property
    def spec(self) -> TaskSpec:
        return self._spec

    @property
    def steps(self) -> int:
        """Control steps taken on the system so far."""
        return self._steps

    @property
    def seconds(self) -> float:
        """Seconds of system time consumed: ``steps * dt``."""
        return self._steps * self._spec.dt

    @property
    def budget_seconds(self) -> float | None:
        return None if self._budget_steps is None else self._budget_steps * self._spec.dt

    @property
    def remaining_steps(self) -> int | None:
        return None if self._budget_steps is None else self._budget_steps - self._steps

    @property
    def episodes(self) -> tuple[Episode, ...]:
        """Completed episodes (an episode cut by the budget is included once it is cut)."""
        return tuple(self._episodes)

    def add_episode_listener(self, callback: Callable[[Episode], None]) -> None:
        """Harness use: ``callback(episode)`` after every completed episode."""
        self._on_episode.append(callback)

    # -- acting ---------------------------------------------------------------------------
    def reset(self) -> np.ndarray:
        """Start a new episode; returns the first observation ``(D,)``. Not counted."""
        self._finish_episode()
        self._started_from = {"seed": self._seed, "env_rng": env_rng_state(self._env) if self._seed is None else None}
        obs, info = self._env.reset(seed=self._seed)
        self._seed = None
        obs = np.asarray(obs, dtype=np.float64)
        self._current = _EpisodeBuffer(obs, _state_of(info, obs))
        self._last_obs = obs
        return obs

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply ``action`` for one control period; gymnasium's 5-tuple. Counted.

        Raises:
            BudgetExhaustedError: the budget is used up (the system does not move).
            InvalidActionError: wrong shape or non-finite action.
            InteractionError: no episode is running (call ``reset`` first).
        """
        if self._current is None:
            raise InteractionError("Interaction.step called before reset(); start an episode with reset()")
        self._check_budget()
        action, _ = check_action(action, self._spec)
        obs, reward, terminated, truncated, info = self._env.step(action)
        self._steps += 1
        obs = np.asarray(obs, dtype=np.float64)
        _record(self._current, obs, reward, terminated, info, action)
        self._last_obs = obs
        if terminated or truncated:
            self._finish_episode()
        return obs, float(reward), bool(terminated), bool(truncated), info

    def rollout(self, policy: Callable[[np.ndarray], Any], max_steps: int | None = None) -> Episode:
        """Run one full episode of ``policy`` (until termination, horizon or ``max_steps``)."""
        obs = self.reset()
        limit = self._spec.horizon if max_steps is None else min(int(max_steps), self._spec.horizon)
        with stepping_threads():
            for _ in range(limit):
                obs, _, terminated, truncated, _ = self.step(policy(obs))
                if terminated or truncated:
                    break
        self._finish_episode()
        return self._episodes[-1]

    def as_env(self) -> gym.Env:
        """A gymnasium view of this interaction (for libraries such as stable-baselines3).

        Every ``step`` of the view is a counted step; ``reset`` starts a new recorded episode.
        """
        return _InteractionEnv(self, self._env.observation_space, self._env.action_space)

    # -- internals ------------------------------------------------------------------------
    def _check_budget(self) -> None:
        if self._budget_steps is not None and self._steps >= self._budget_steps:
            self._finish_episode()
            raise BudgetExhaustedError(
                f"interaction budget of {self.budget_seconds:g} s ({self._budget_steps} steps of "
                f"{self._spec.dt:g} s) is used up; raise --budget-seconds to allow more"
            )

    def _finish_episode(self) -> None:
        if self._current is not None and self._current.actions:
            episode = self._current.to_episode(self._spec)
            self._episodes.append(episode)
            for callback in self._on_episode:
                callback(episode)
        self._current = None

    @property
    def can_checkpoint(self) -> bool:
        """Whether :meth:`state_dict` can be taken now: between episodes, or after a reset before the
        episode's first step (a step changes the system's state, which is not saved)."""
        return self._current is None or not self._current.actions

    def state_dict(self) -> dict[str, Any]:
        """Counters, recorded episodes (each a dict of its fields) and the environment's RNG state, as
        plain data (:mod:`harness.datafile`). Between episodes, or with an episode started and no step
        taken: then as it was before that reset (where stable-baselines3 hands over, its vectorised env
        having reset at the episode's end; after the resume its first ``reset`` draws the same start)."""
        if not self.can_checkpoint:
            raise InteractionError("cannot checkpoint an interaction in the middle of an episode "
                                   "(only between episodes, or after a reset before the first step)")
        episodes = [{f.name: getattr(ep, f.name) for f in fields(Episode)} for ep in self._episodes]
        if self._current is not None:  # started, not stepped: saved as it was before its reset
            return {"steps": self._steps, "episodes": episodes, "seed": self._started_from["seed"],
                    "env_rng": self._started_from["env_rng"]}
        return {"steps": self._steps, "episodes": episodes, "seed": self._seed, "env_rng": env_rng_state(self._env)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict` (same task variant; the budget stays this object's)."""
        self._steps = int(state["steps"])
        self._episodes = [Episode(**ep) for ep in state["episodes"]]
        self._seed = state["seed"]
        self._current = None
        if self._seed is None:  # the first reset already happened: restore the RNG it left
            self._env.reset(seed=0)  # materialise the env's generators, then overwrite them
            set_env_rng_state(self._env, state["env_rng"])

    def close(self) -> None:
        self._finish_episode()
        self._env.close()


def env_rng_state(env: gym.Env) -> Any:
    """The environment's random state: its own ``rng_state()`` if it has one, else ``np_random``'s."""
    inner = env.unwrapped
    if callable(getattr(inner, "rng_state", None)):
        return inner.rng_state()
    return inner.np_random.bit_generator.state


def set_env_rng_state(env: gym.Env, state: Any) -> None:
    """Inverse of :func:`env_rng_state`."""
    inner = env.unwrapped
    if callable(getattr(inner, "set_rng_state", None)):
        inner.set_rng_state(state)
    else:
        inner.np_random.bit_generator.state = state


class _InteractionEnv(gym.Env):
    """Gymnasium facade whose steps go through (and are counted by) an :class:`Interaction`."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, interaction: Interaction, observation_space: gym.Space, action_space: gym.Space) -> None:
        self._interaction = interaction
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return self._interaction.reset(), {}

    def step(self, action):
        return self._interaction.step(action)
