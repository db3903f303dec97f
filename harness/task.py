"""The task plugin API: what a task tells learners, and what the harness needs to run it.

A task is a controlled dynamical system with

* a gymnasium environment (``Task.make_env``) whose observation is the state vector ``x``
  (shape ``(D,)``), whose action is the control ``u`` (shape ``(F,)``, seconds of system time per
  step ``dt``), and whose reward is ``-cost(x_next)`` for the true (noise-free) next state;
* the data a model-based learner plans with (:class:`TaskSpec`): initial state distribution
  ``N(init_mean, init_cov)``, control bounds, horizon, which entries of ``x`` are angles, and the
  cost *as data* (:class:`SaturatingCost`) so that the reward of the environment and a closed-form
  expected cost are computed from one definition;
* a per-episode success predicate (``Task.success``).

Environment contract (checked by :mod:`harness.testing`):

* ``reset(seed=...)`` -> ``(obs, info)`` with ``info["state"]`` the true state (obs may carry
  measurement noise);
* ``step(u)`` -> ``(obs, reward, terminated, truncated, info)`` with ``reward == -spec.cost(info["state"])``,
  ``truncated`` true after ``spec.horizon`` steps, ``terminated`` true when the system left its
  allowed region (e.g. the unicycle fell), ``info["action_clipped"]`` true if ``u`` was clipped to
  the bounds. Non-finite or wrongly shaped actions raise :class:`~harness.errors.InvalidActionError`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from harness.errors import InvalidActionError
from harness.options import Option, OptionSet


@dataclass(frozen=True)
class SaturatingCost:
    """Saturating cost c(x) = 1 - exp(-1/2 (a(x) - z)^T W (a(x) - z)), in [0, 1).

    The cost acts on the *cost features* of a state ``x`` (shape ``(D,)``)::

        phi  = angle_map @ x                       # (K,) angles whose sin/cos enter the cost
        a(x) = [x, sin(phi), cos(phi)]              # (D + 2K,)
        r(x) = linear_map @ a(x) - target           # (P,) residual, e.g. pole-tip offset in metres
        c(x) = 1 - exp(-|r(x)|^2 / (2 width^2))

    so ``W = linear_map^T linear_map / width^2`` and ``z`` is any ``a`` with ``linear_map @ a = target``.

    Width convention: **with the factor 1/2**, as the reference implementation's ``lossSat``
    (``c = 1 - exp(-d^2 / (2 sigma_c^2))``); the paper's eq. (25) writes ``exp(-d^2/sigma_c^2)``, which
    is narrower by sqrt(2). Per-term weights (e.g. the unicycle's 8, 1/2, 1/2) are folded into
    the rows of ``linear_map`` as their square roots.

    Attributes:
        angle_map: ``(K, D)``; ``K = 0`` when no trigonometric features are needed.
        linear_map: ``(P, D + 2K)``.
        target: ``(P,)``.
        width: ``sigma_c > 0``, in the units of the residual.
    """

    angle_map: np.ndarray
    linear_map: np.ndarray
    target: np.ndarray
    width: float

    def __post_init__(self) -> None:
        angle_map = np.atleast_2d(np.asarray(self.angle_map, dtype=np.float64))
        linear_map = np.atleast_2d(np.asarray(self.linear_map, dtype=np.float64))
        target = np.asarray(self.target, dtype=np.float64).reshape(-1)
        object.__setattr__(self, "angle_map", angle_map)
        object.__setattr__(self, "linear_map", linear_map)
        object.__setattr__(self, "target", target)
        if not self.width > 0:
            raise ValueError(f"cost width must be > 0, got {self.width}")
        n_angles, dim = angle_map.shape
        if linear_map.shape[1] != dim + 2 * n_angles:
            raise ValueError(
                f"linear_map has {linear_map.shape[1]} columns; expected D + 2K = {dim + 2 * n_angles}"
            )
        if linear_map.shape[0] != target.shape[0]:
            raise ValueError("linear_map rows and target length differ")

    @property
    def state_dim(self) -> int:
        """D, the state dimension this cost is defined on."""
        return self.angle_map.shape[1]

    @property
    def weight(self) -> np.ndarray:
        """W = C^T C / width^2, shape ``(D + 2K, D + 2K)``."""
        return self.linear_map.T @ self.linear_map / self.width**2

    def features(self, x: np.ndarray) -> np.ndarray:
        """a(x) = [x, sin(A x), cos(A x)]; ``x`` of shape ``(..., D)`` -> ``(..., D + 2K)``."""
        x = np.asarray(x, dtype=np.float64)
        phi = x @ self.angle_map.T
        return np.concatenate([x, np.sin(phi), np.cos(phi)], axis=-1)

    def residual(self, x: np.ndarray) -> np.ndarray:
        """r(x) = C a(x) - target, ``(..., D)`` -> ``(..., P)``."""
        return self.features(x) @ self.linear_map.T - self.target

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """c(x) for ``x`` of shape ``(..., D)``; returns shape ``(...)``."""
        r = self.residual(x)
        return 1.0 - np.exp(-0.5 * np.sum(r * r, axis=-1) / self.width**2)

    def with_width(self, width: float) -> SaturatingCost:
        """The same cost with another width (a learner may plan with a different width)."""
        return SaturatingCost(self.angle_map, self.linear_map, self.target, float(width))


@dataclass(frozen=True)
class TaskSpec:
    """Everything a learner may know about a task. Learners never get the environment itself.

    Attributes:
        name: task name (entry-point name), e.g. ``"cartpole"``.
        state_names: names of the ``D`` state entries (the observation), with units.
        action_names: names of the ``F`` controls, with units.
        dt: seconds of system time per control step (zero-order hold).
        horizon: steps per episode ``H`` (an episode lasts ``H * dt`` seconds unless terminated).
        action_low, action_high: control bounds, shape ``(F,)``.
        init_mean, init_cov: initial state distribution ``N(init_mean, init_cov)``, shapes
            ``(D,)`` and ``(D, D)``, in observation coordinates.
        angle_indices: indices of ``x`` that are angles (a learner may use sin/cos of them).
        cost: the task's cost; the environment's reward is ``-cost(x)``.
        measurement_noise_std: std of the Gaussian noise on observations, shape ``(D,)``.
        options: the resolved task options (the *variant*), recorded with every run.
        physical_state_dim: dimension of the simulated state if it differs from ``D``
            (the unicycle integrates 12 ODEs but exposes the reference's 10 planning states).
    """

    name: str
    state_names: tuple[str, ...]
    action_names: tuple[str, ...]
    dt: float
    horizon: int
    action_low: np.ndarray
    action_high: np.ndarray
    init_mean: np.ndarray
    init_cov: np.ndarray
    angle_indices: tuple[int, ...]
    cost: SaturatingCost
    measurement_noise_std: np.ndarray
    options: Mapping[str, Any] = field(default_factory=dict)
    physical_state_dim: int | None = None

    def __post_init__(self) -> None:
        for key in ("action_low", "action_high", "init_mean", "init_cov", "measurement_noise_std"):
            object.__setattr__(self, key, np.asarray(getattr(self, key), dtype=np.float64))
        d, f = self.state_dim, self.action_dim
        if self.init_mean.shape != (d,) or self.init_cov.shape != (d, d):
            raise ValueError(f"{self.name}: init_mean/init_cov must have shapes ({d},) and ({d},{d})")
        if self.action_low.shape != (f,) or self.action_high.shape != (f,):
            raise ValueError(f"{self.name}: action bounds must have shape ({f},)")
        if np.any(self.action_low >= self.action_high):
            raise ValueError(f"{self.name}: action_low must be < action_high")
        if self.measurement_noise_std.shape != (d,):
            raise ValueError(f"{self.name}: measurement_noise_std must have shape ({d},)")
        if self.cost.state_dim != d:
            raise ValueError(f"{self.name}: cost is defined on {self.cost.state_dim} states, task has {d}")
        if not (self.dt > 0 and self.horizon > 0):
            raise ValueError(f"{self.name}: dt and horizon must be positive")

    @property
    def state_dim(self) -> int:
        """D."""
        return len(self.state_names)

    @property
    def action_dim(self) -> int:
        """F."""
        return len(self.action_names)

    @property
    def episode_seconds(self) -> float:
        """Seconds of system time in a full episode, ``horizon * dt``."""
        return self.horizon * self.dt


@dataclass
class Episode:
    """One episode as recorded by the harness.

    Attributes:
        observations: ``(T+1, D)`` what the policy saw (with measurement noise).
        states: ``(T+1, D)`` true states (no noise); ``states[0]`` is the initial state.
        actions: ``(T, F)`` controls applied (after clipping to the bounds).
        costs: ``(T,)`` ``cost(states[t+1])``, i.e. ``-reward`` of step ``t``.
        terminated: the system left its allowed region before the horizon.
        clipped_actions: number of steps whose action was clipped to the bounds.
        extra: per-task additions (e.g. the dm_control episode return).
    """

    observations: np.ndarray
    states: np.ndarray
    actions: np.ndarray
    costs: np.ndarray
    terminated: bool = False
    clipped_actions: int = 0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        """T, the number of control steps taken."""
        return int(self.actions.shape[0])

    @property
    def total_cost(self) -> float:
        """Sum of the per-step costs of the steps taken."""
        return float(np.sum(self.costs))

    def horizon_cost(self, horizon: int) -> float:
        """Summed cost over the first ``horizon`` steps, the measure evaluations report (over the task's
        horizon) and learners compare with a prediction over their planning horizon.

        A terminated episode holds its last cost for the ``horizon - steps`` steps it did not take
        (the region it left is absorbing: a fallen unicycle stays fallen). Without this, a policy
        that fails *sooner* would score a *lower* cost. Untruncated episodes: :attr:`total_cost`.
        """
        return held_cost(self.costs[:horizon], horizon, self.terminated)


def held_cost(costs: np.ndarray, horizon: int, terminated: bool) -> float:
    """Sum of per-step ``costs``; if the episode ``terminated`` after fewer than ``horizon`` steps, its last
    cost held for the steps it did not take (:meth:`Episode.horizon_cost`, which applies it to the task's cost)."""
    costs = np.asarray(costs, dtype=float).reshape(-1)
    missing = max(horizon - costs.size, 0) if terminated and costs.size else 0
    return float(np.sum(costs)) + missing * float(costs[-1]) if missing else float(np.sum(costs))


class Task(ABC):
    """Base class of task plugins.

    Subclasses set the class attributes and implement :meth:`spec`, :meth:`make_env` and
    :meth:`success`. Options (the task *variant*) are declared in ``options`` and arrive
    validated in ``self.options``.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    options: ClassVar[tuple[Option, ...]] = ()
    #: the pip extra this task needs, e.g. ``"dmc"``; used in "not installed" hints.
    extra: ClassVar[str | None] = None
    #: top-level modules this plugin needs at use time (checked by discovery, e.g. ``("dm_control",)``).
    requires: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **options: Any) -> None:
        self.options: dict[str, Any] = self.option_set().resolve(options)

    @classmethod
    def option_set(cls) -> OptionSet:
        return OptionSet(cls.options, f"task '{cls.name}'")

    @property
    @abstractmethod
    def spec(self) -> TaskSpec:
        """The task's :class:`TaskSpec` for the resolved options."""

    @abstractmethod
    def make_env(self, render_mode: str | None = None):
        """A new, independent gymnasium environment following the module's contract."""

    @abstractmethod
    def success(self, episode: Episode) -> bool:
        """Whether one episode met the task's success criterion (documented by the subclass)."""

    def goal_distance(self, state: np.ndarray) -> float | None:
        """Distance (metres) of the task's reference point (pole tip, top of the frame) from its
        goal in the true state ``(D,)``, for test histograms; ``None`` if the task defines none."""
        return None


def check_action(action: Any, spec: TaskSpec) -> tuple[np.ndarray, bool]:
    """Validate an action and clip it to the bounds.

    Returns ``(clipped, was_clipped)``. Raises :class:`InvalidActionError` for a wrong shape or a
    non-finite entry, naming the task and the expected shape.
    """
    try:
        u = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidActionError(
            f"{spec.name}: action {action!r} is not numeric; expected an array of shape ({spec.action_dim},)"
        ) from None
    if u.shape == () and spec.action_dim == 1:
        u = u.reshape(1)
    if u.shape != (spec.action_dim,):
        raise InvalidActionError(
            f"{spec.name}: action has shape {u.shape}; expected ({spec.action_dim},) "
            f"for controls {', '.join(spec.action_names)}"
        )
    if not np.all(np.isfinite(u)):
        raise InvalidActionError(
            f"{spec.name}: action {u.tolist()} contains NaN or inf; the learner produced a non-finite control"
        )
    clipped = np.clip(u, spec.action_low, spec.action_high)
    return clipped, bool(np.any(clipped != u))
