"""The shared success predicate against a brute-force reading of its two rules."""

import numpy as np
import pytest

from tasks.success import held_within


def _brute(d: np.ndarray, radius: float, steps: int, rule: str) -> bool:
    if len(d) < steps:
        return False
    if rule == "final":
        return all(x <= radius for x in d[-steps:])
    return any(all(x <= radius for x in d[i : i + steps]) for i in range(len(d) - steps + 1))


@pytest.mark.parametrize("rule", ["consecutive", "final"])
def test_held_within_matches_brute_force(rule):
    rng = np.random.default_rng(0)
    for _ in range(500):
        d = rng.uniform(0, 0.2, size=rng.integers(0, 30)) * (rng.uniform() < 0.5 or 0.5)
        assert held_within(d, 0.08, 4, rule) == _brute(d, 0.08, 4, rule)


def test_unknown_rule_is_named():
    with pytest.raises(ValueError, match="unknown success rule 'often'"):
        held_within(np.zeros(20), 0.1, 10, "often")
