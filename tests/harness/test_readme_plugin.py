"""The plugin example of docs/plugins.md passes the learner conformance suite."""

from __future__ import annotations

import re
from pathlib import Path

from harness.testing import check_learner, check_policy_round_trip
from tasks.cartpole import CartPole


def test_the_readme_learner_example_passes_the_conformance_checks():
    readme = (Path(__file__).resolve().parents[2] / "docs" / "plugins.md").read_text()
    (source,) = re.findall(r"```python\n(# my_package/constant\.py\n.*?)```", readme, flags=re.S)
    namespace: dict = {}
    exec(compile(source, "docs/plugins.md (my_package/constant.py)", "exec"), namespace)
    learner_cls = namespace["ConstantLearner"]
    check_learner(learner_cls, CartPole(horizon=10), {"level": 1.0})
    check_policy_round_trip(learner_cls, CartPole(horizon=10), {"level": 1.0})
