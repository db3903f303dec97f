"""PILCO beside the model-free baselines (SAC, PPO): how a row's runs did, and how many times less
interaction PILCO needed than the best model-free learner (Table 1's last columns)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from harness.report.formatting import fmt_seconds
from harness.report.records import RunRecord
from harness.statistics import median, times_with_failures

#: the model-free learners Table 1 sets beside PILCO, each a column
MODEL_FREE = ("sac", "ppo")


@dataclass(frozen=True)
class Outcome:
    """A row's counted runs: how many solved, the median interaction time to success with unsolved
    runs as ``+inf``, and the least interaction an unsolved run consumed (``nan`` if none)."""

    label: str
    runs: int
    solved: int
    median_s: float
    unsolved_min_s: float


def outcome(label: str, runs: Sequence[RunRecord]) -> Outcome:
    """The :class:`Outcome` of ``runs`` (at least one)."""
    times = times_with_failures([r.solved for r in runs], [r.time_to_success for r in runs])
    unsolved = [r.interaction_seconds for r in runs if not r.solved]
    return Outcome(label, len(runs), sum(r.solved for r in runs), float(median(times)), min(unsolved, default=math.nan))


def _rank(o: Outcome) -> tuple[float, int, float]:
    """Best first: the lowest median, then the most solved, then the most interaction given to the unsolved."""
    return (o.median_s, -o.solved, -(o.unsolved_min_s if math.isfinite(o.unsolved_min_s) else 0.0))


def best_outcome(by_label: dict[str, list[RunRecord]], learner: str) -> Outcome | None:
    """The best of ``learner``'s rows on a task (several where it ran in differently configured sweeps); ``None`` if it did not run."""
    rows = [outcome(label, runs) for label, runs in by_label.items() if runs and runs[0].learner == learner]
    return min(rows, key=_rank, default=None)


def fmt_outcome(o: Outcome | None) -> str:
    """``'2/3, 12.0 s'``, ``'1/3, ∞ (≥ 40.0 s)'`` (median not reached, the unsolved runs' least interaction), or ``'not run'``."""
    if o is None:
        return "not run"
    text = f"{o.solved}/{o.runs}, {fmt_seconds(o.median_s)}"
    return text + f" (≥ {fmt_seconds(o.unsolved_min_s)} s)" if math.isinf(o.median_s) else text + " s"


def pilco_vs_model_free(pilco: Outcome | None, baselines: Sequence[Outcome | None]) -> str:
    """How many times less interaction PILCO needed than the best model-free baseline (ratio of the
    medians, unsolved = ∞); where that baseline's median is not reached, the interaction its unsolved
    runs consumed is a lower bound; ``'—'`` without counted PILCO runs or without a baseline."""
    ran = [b for b in baselines if b is not None]
    if pilco is None or not ran:
        return "—"
    best = min(ran, key=_rank)
    if math.isfinite(best.median_s):
        if math.isinf(pilco.median_s):
            return f"PILCO median not reached (≥ {fmt_seconds(pilco.unsolved_min_s)} s; {best.label}: {fmt_seconds(best.median_s)} s)"
        return f"{best.median_s / pilco.median_s:.1f}× less than {best.label}"
    what = "never solved" if not any(b.solved for b in ran) else "median not reached"
    text = f"baseline {what} within its budget (≥ {fmt_seconds(best.unsolved_min_s)} s)"
    return text + (f"; ≥ {best.unsolved_min_s / pilco.median_s:.1f}× less" if math.isfinite(pilco.median_s) else "")
