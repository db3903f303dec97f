"""The planning horizon over a run: fixed, or a schedule that doubles it (up to the task's horizon).

PILCO's J sums the predicted cost over the planning horizon. On the unicycle the task's 67 steps
give a flat objective around the start policy, so its preset plans over 20 steps first and doubles
the horizon once the policy does well over the shorter one. What "does well" means is the rule
(learner option ``grow_horizon_on``), judged once per trial against ``grow_horizon_below``:

- ``prediction``: the search just done predicts a mean cost per step ``J/horizon`` below it;
- ``survival``: the real episode of the policy just applied stayed up for all planned steps (the
  threshold then only switches the schedule on);
- ``realised``: that real episode cost less than the threshold per planned step, a fall within them
  holding its last cost (:func:`realised_cost_per_step`).

The two real-episode rules act after the trial's rollout, before its model is trained; the
prediction rule after the trial's policy search. :class:`HorizonSchedule` holds the current horizon
and applies the rule at both points; the functions are the rules themselves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from harness.options import Option
from harness.task import Episode

#: the values of the learner option ``grow_horizon_on``
RULES = ("prediction", "survival", "realised")

#: the learner option that picks the rule (``pilco`` and ``mc-pilco``)
GROW_HORIZON_ON = Option(
    "grow_horizon_on", str, "prediction", "when the horizon schedule (grow_horizon_below > 0) doubles the planning horizon: "
    "prediction (after a search whose J/horizon is below grow_horizon_below) or survival (after a trial whose real episode "
    "was not aborted within the planning horizon; the threshold then only switches the schedule on) or realised (after a "
    "trial whose real episode's mean cost per step over the planning horizon, a fall holding its last cost, is below "
    "grow_horizon_below)", choices=RULES)


class _Search(Protocol):
    J_after: float


def doubled_horizon(horizon: int, task_horizon: int) -> int:
    """A horizon schedule's step: ``horizon`` doubled, up to ``task_horizon``; unchanged once there (or beyond)."""
    return horizon if horizon >= task_horizon else min(2 * horizon, task_horizon)


def next_planning_horizon(horizon: int, task_horizon: int, search: _Search | None, grow_below: float | None) -> int:
    """The planning horizon (steps) for the next trial under the ``prediction`` rule: doubled, up to
    ``task_horizon``, when ``grow_below`` is set and the search just done predicts a mean cost per step
    ``J/horizon`` below it (the policy already does well over the shorter horizon); otherwise unchanged."""
    if grow_below is None or search is None or not search.J_after / horizon < grow_below:  # a NaN J: no growth
        return horizon
    return doubled_horizon(horizon, task_horizon)


def survived_horizon(horizon: int, task_horizon: int, episode: Episode) -> int:
    """The planning horizon (steps) under the ``survival`` rule: doubled, up to ``task_horizon``, when
    the real ``episode`` of the policy just applied stayed in the task's region for all ``horizon``
    planned steps (it was not aborted before them: reality, not the model, says the policy already
    holds over the shorter horizon); otherwise unchanged."""
    if episode.terminated and episode.steps < horizon:
        return horizon
    return doubled_horizon(horizon, task_horizon)


def realised_cost_per_step(horizon: int, episode: Episode) -> float:
    """The real ``episode``'s mean cost per step over its first ``horizon`` steps, a fall within them
    holding its last cost for the steps not taken (:meth:`harness.task.Episode.horizon_cost`, as evaluations count)."""
    return episode.horizon_cost(horizon) / horizon


def realised_horizon(horizon: int, task_horizon: int, episode: Episode, grow_below: float) -> int:
    """The planning horizon (steps) under the ``realised`` rule: doubled, up to ``task_horizon``, when the
    real ``episode`` of the policy just applied had a mean cost per step below ``grow_below`` over the
    ``horizon`` planned steps (:func:`realised_cost_per_step`). Reality, not the model, judges the
    policy over the shorter horizon, and unlike the ``survival`` rule an episode that stayed up far from
    the goal (or fell) does not count as doing well."""
    if realised_cost_per_step(horizon, episode) >= grow_below:
        return horizon
    return doubled_horizon(horizon, task_horizon)


@dataclass
class HorizonSchedule:
    """The planning horizon of a run (steps) and the rule that grows it.

    Attributes:
        horizon: the current planning horizon, steps.
        task_horizon: the task's horizon, steps (the schedule stops there).
        grow_below: the rule's threshold, cost per step; ``None``: the horizon stays fixed.
        rule: one of :data:`RULES`.
    """

    horizon: int
    task_horizon: int
    grow_below: float | None = None
    rule: str = "prediction"

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"horizon rule {self.rule!r} is not one of {', '.join(RULES)}")

    def after_rollout(self, episode: Episode) -> float:
        """Apply a real-episode rule to the ``episode`` just recorded; return its mean cost per step over
        the horizon it was planned for (:func:`realised_cost_per_step`, logged by the learner)."""
        realised = realised_cost_per_step(self.horizon, episode)
        if self.grow_below is not None and self.rule == "survival":
            self.horizon = survived_horizon(self.horizon, self.task_horizon, episode)
        elif self.grow_below is not None and self.rule == "realised":
            self.horizon = realised_horizon(self.horizon, self.task_horizon, episode, self.grow_below)
        return realised

    def after_search(self, search: _Search | None) -> None:
        """Apply the ``prediction`` rule to the policy search just done (``None``, or a non-finite J: it failed)."""
        if self.rule == "prediction":
            self.horizon = next_planning_horizon(self.horizon, self.task_horizon, search, self.grow_below)
