"""benchmarks/planning_cost_check.py: the realised cost of a recorded episode is what the harness's
evaluation would score over the same horizon, falls included."""

from __future__ import annotations

import numpy as np

from benchmarks.planning_cost_check import realised_cost
from harness.interaction import run_episode
from tasks.unicycle import Unicycle


def test_a_fall_holds_its_last_cost_as_the_evaluation_scores_it():
    """A unicycle without torque falls within the horizon: summed over the task's horizon with the task's cost,
    the realised cost equals the episode's own horizon_cost (the last cost held), not the cheaper sum of the
    steps taken; over fewer steps than it took, nothing is added."""
    task = Unicycle()
    spec = task.spec
    episode = run_episode(task.make_env(), spec, lambda obs: np.zeros(spec.action_dim), seed=3)
    assert episode.terminated and 1 < episode.steps < spec.horizon  # not vacuous: a fall before the horizon
    held = realised_cost(spec.cost, episode, spec.horizon)
    np.testing.assert_allclose(held, episode.horizon_cost(spec.horizon), rtol=1e-12)
    assert held > episode.total_cost + 0.5 * (spec.horizon - episode.steps)  # the fallen state costs ~1 per step
    short = episode.steps - 1
    np.testing.assert_allclose(realised_cost(spec.cost, episode, short), np.sum(episode.costs[:short]), rtol=1e-12)
    wider = spec.cost.with_width(2 * spec.cost.width)  # a planning width: its own last cost is held
    costs = np.asarray(wider(np.asarray(episode.states)[1:]))
    np.testing.assert_allclose(realised_cost(wider, episode, spec.horizon),
                               costs.sum() + (spec.horizon - episode.steps) * costs[-1], rtol=1e-12)
