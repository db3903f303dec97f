"""benchmarks/fresh_start_replay.py: the replay pairs each trial's J with the previous one and the previous
policy's own episode with its prediction, as the learner does."""

from __future__ import annotations

import numpy as np

from benchmarks.fresh_start_replay import fires


def test_fires_where_the_learners_rule_would():
    J = {1: 50.0, 2: 49.9, 3: 45.0, 4: 44.9}
    predicted = {1: 55.0, 2: 50.0, 3: 40.0}
    episodes_before = {1: 1, 2: 2, 3: 3, 4: 4}  # one random episode, then one per policy
    costs = [np.array([c]) for c in (60.0, 55.5, 50.2, 47.0)]  # episode 1 is policy 1's, episode 2 policy 2's, ...
    # trial 2: J moved 0.2 %, policy 1's episode 55.5 against 55.0 predicted (0.9 %); trial 3: J moved 10 %;
    # trial 4: J moved 0.2 % but policy 3's episode 47.0 against 40.0 predicted (15 %)
    assert fires(J, predicted, episodes_before, costs, tol=0.05) == [2]
    assert fires(J, predicted, episodes_before, costs, tol=0.005) == []  # 0.9 % > 0.5 %
    assert fires(J, predicted, episodes_before, costs, tol=0.2) == [2, 3, 4]  # trial 3: 9.8 % and 0.4 %


def test_missing_data_never_fires():
    costs = [np.array([1.0]), np.array([50.0])]
    assert fires({1: 50.0, 2: 50.0}, {}, {2: 2}, costs, tol=0.5) == []  # no prediction for policy 1
    assert fires({1: 50.0, 2: 50.0}, {1: 50.0}, {2: 5}, costs, tol=0.5) == []  # its episode is not stored


def test_realised_cost_over_the_predictions_own_horizon():
    """With a growing planning horizon, policy k-1's episode is summed over the steps its prediction covered."""
    J, predicted, before = {1: 10.0, 2: 10.0}, {1: 10.0}, {2: 2}
    costs = [np.ones(60), np.ones(60)]  # policy 1's episode: 1 per step
    assert fires(J, predicted, before, costs, tol=0.05, horizon={1: 10, 2: 20}) == [2]  # 10 steps: 10 against 10
    assert fires(J, predicted, before, costs, tol=0.05) == []  # all 60 steps: 60 against 10
