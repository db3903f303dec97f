"""The random learner passes the learner conformance suite on the real cart-pole."""

from __future__ import annotations

from harness.runner import run_from_names
from harness.testing import LearnerConformance
from plugins.random_learner import RandomLearner


class TestRandomLearner(LearnerConformance):
    learner_cls = RandomLearner
    task_name = "cartpole"


def test_random_never_solves_cartpole_and_counts_its_episodes():
    result = run_from_names("random", "cartpole", seed=1, max_trials=3, eval_episodes=2)
    assert not result.solved and result.interaction_seconds == 12.0 and result.interaction_episodes == 3
