"""Evaluation cost over the task horizon: a terminated episode holds its last cost."""

import numpy as np

from harness.evaluation import Evaluator
from harness.task import Episode
from tasks.unicycle import Unicycle


def _episode(costs, terminated):
    t = len(costs)
    return Episode(np.zeros((t + 1, 1)), np.zeros((t + 1, 1)), np.zeros((t, 1)), np.asarray(costs, float), terminated)


def test_horizon_cost_pads_terminated_episodes_with_their_last_cost():
    assert _episode([0.5, 0.9], terminated=True).horizon_cost(5) == 0.5 + 0.9 + 3 * 0.9
    assert _episode([0.5, 0.9], terminated=False).horizon_cost(5) == 1.4  # truncated by a step limit: nothing added
    assert _episode([0.1] * 5, terminated=True).horizon_cost(5) == 0.5  # terminated on the last step
    assert _episode([0.1] * 5 + [1.0] * 3, terminated=True).horizon_cost(5) == 0.5  # only the first 5 steps count


def test_unicycle_evaluation_charges_a_fall_for_the_rest_of_the_horizon():
    """Zero torque from the paper's start: the unicycle falls within about a second.

    Charged over the 67 steps the fallen state costs ~1 per step, so the evaluation cost is close
    to the horizon, not the handful of steps taken (the old measure, where falling sooner looked better).
    """
    task = Unicycle()
    evaluator = Evaluator(task, n_episodes=5, seed=3)
    result = evaluator(lambda obs: np.zeros(2))
    horizon = task.spec.horizon
    assert all(ep.terminated and ep.steps < 15 for ep in result.episodes)
    expected = np.mean([ep.costs.sum() + (horizon - ep.steps) * ep.costs[-1] for ep in result.episodes])
    assert result.mean_cost == expected
    assert result.mean_cost > 0.8 * horizon > 5 * np.mean([ep.total_cost for ep in result.episodes])
