"""benchmarks/fresh_start_replay.py: the replay pairs each trial's J with the previous one and the previous
policy's own episode with its prediction, as the learner does."""

from __future__ import annotations

from benchmarks.fresh_start_replay import fires


def test_fires_where_the_learners_rule_would():
    J = {1: 50.0, 2: 49.9, 3: 45.0, 4: 44.9}
    predicted = {1: 55.0, 2: 50.0, 3: 40.0}
    episodes_before = {1: 1, 2: 2, 3: 3, 4: 4}  # one random episode, then one per policy
    costs = [60.0, 55.5, 50.2, 47.0]  # episode 1 is policy 1's, episode 2 policy 2's, ...
    # trial 2: J moved 0.2 %, policy 1's episode 55.5 against 55.0 predicted (0.9 %); trial 3: J moved 10 %;
    # trial 4: J moved 0.2 % but policy 3's episode 47.0 against 40.0 predicted (15 %)
    assert fires(J, predicted, episodes_before, costs, tol=0.05) == [2]
    assert fires(J, predicted, episodes_before, costs, tol=0.005) == []  # 0.9 % > 0.5 %
    assert fires(J, predicted, episodes_before, costs, tol=0.2) == [2, 3, 4]  # trial 3: 9.8 % and 0.4 %


def test_missing_data_never_fires():
    assert fires({1: 50.0, 2: 50.0}, {}, {2: 2}, [1.0, 50.0], tol=0.5) == []  # no prediction for policy 1
    assert fires({1: 50.0, 2: 50.0}, {1: 50.0}, {2: 5}, [1.0, 50.0], tol=0.5) == []  # its episode is not stored
