"""Evaluation of a handed-over policy on the harness's own environment instance.

Evaluation steps are never counted as interaction: they run on a separate environment that the
learner never sees. Every evaluation of a run uses the same ``n_episodes`` initial-state seeds
(common random numbers), so success rates of successive policies are compared on equal terms.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.interaction import run_episode
from harness.task import Episode, Task

#: the task counts as solved when at least this fraction of evaluation episodes succeed
SOLVED_FRACTION = 0.9


@dataclass
class EvaluationResult:
    """Outcome of one evaluation.

    Attributes:
        success_rate: fraction of episodes that met the task's success predicate.
        mean_cost: mean over episodes of the summed per-step cost over the task horizon
            (:meth:`~harness.task.Episode.horizon_cost`: a terminated episode holds its last cost).
        solved: ``success_rate >= SOLVED_FRACTION``.
        episodes: the evaluation episodes.
    """

    success_rate: float
    mean_cost: float
    solved: bool
    episodes: list[Episode]

    @property
    def mean_extra(self) -> dict[str, float]:
        """Per-task extras averaged over episodes (e.g. ``dmc_reward`` = dm_control return)."""
        keys = {k for ep in self.episodes for k in ep.extra}
        return {k: float(np.mean([ep.extra.get(k, 0.0) for ep in self.episodes])) for k in sorted(keys)}


class Evaluator:
    """Runs ``n_episodes`` of a policy on a dedicated environment of ``task``.

    Args:
        task: the task (its ``make_env`` builds the evaluation environment).
        n_episodes: episodes per evaluation (default 10).
        seed: base seed; episode ``i`` starts from ``reset(seed=seed + i)``.
    """

    def __init__(self, task: Task, n_episodes: int = 10, seed: int = 0) -> None:
        if n_episodes < 1:
            raise ValueError("n_episodes must be >= 1")
        self.task = task
        self.spec = task.spec
        self.n_episodes = int(n_episodes)
        self.seed = int(seed)
        self._env = task.make_env()

    def __call__(self, policy: Callable[[np.ndarray], Any]) -> EvaluationResult:
        episodes = [run_episode(self._env, self.spec, policy, seed=self.seed + i) for i in range(self.n_episodes)]
        successes = [bool(self.task.success(ep)) for ep in episodes]
        rate = float(np.mean(successes))
        return EvaluationResult(
            success_rate=rate,
            mean_cost=float(np.mean([ep.horizon_cost(self.spec.horizon) for ep in episodes])),
            solved=rate >= SOLVED_FRACTION,
            episodes=episodes,
        )

    def close(self) -> None:
        self._env.close()
