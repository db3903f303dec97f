"""benchmarks/search_outcome_check.py: which trials' searches ended above their start."""

from __future__ import annotations

from benchmarks.search_outcome_check import search_changes, searches_above_start


class _Run:
    """A run reader's ``history`` for two metrics, as the store returns it (``{trial: value}``)."""

    def __init__(self, before: dict[int, float], after: dict[int, float]) -> None:
        self._h = {"J_before": before, "J_after": after}

    def history(self, key: str) -> dict[int, float]:
        return self._h[key]


def test_only_searches_ending_more_than_the_margin_above_their_start_count():
    """Trial 2 ends 5 above its start, trial 3 exactly at the margin (not counted), trial 1 below, trial 4
    has no J_after (a search that did not finish): only trial 2 is reported, with its difference."""
    changes = search_changes(_Run({1: 10.0, 2: 8.0, 3: 7.0, 4: 6.0}, {1: 6.0, 2: 13.0, 3: 8.0}))
    assert changes == {1: -4.0, 2: 5.0, 3: 1.0}
    assert searches_above_start(changes, 1.0) == [(2, 5.0)]
    assert searches_above_start(changes, 0.5) == [(2, 5.0), (3, 1.0)]
