"""Aggregate statistics over seeds for times to success, where an unsolved run counts as +inf.

An unsolved run has no time to success; it is censored at the interaction it used. Counting it
as ``+inf`` keeps it in every statistic instead of dropping it: the median is finite only if
more than half of the runs solved, the IQM (mean of the middle 50 %) only if at most
``floor(n / 4)`` runs are unsolved. Sorting-based statistics (median, quantiles without
interpolation, trimmed means) are exact with ``inf``; means and linear interpolation are not,
so the confidence intervals use order statistics.

Confidence intervals follow rliable (Agarwal et al., NeurIPS 2021): a percentile bootstrap over
runs, stratified by task (runs are resampled with replacement within each task, never across),
with a seeded generator so that a report is reproducible.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

Statistic = Callable[[np.ndarray], np.ndarray]


def median(x: np.ndarray) -> np.ndarray:
    """Median over the last axis; ``(..., n) -> (...)``; exact with ``+inf`` entries."""
    return np.median(np.asarray(x, dtype=np.float64), axis=-1)


def iqm(x: np.ndarray) -> np.ndarray:
    """Interquartile mean over the last axis: the mean after dropping ``floor(n/4)`` values at
    each end (``scipy.stats.trim_mean(x, 0.25)``); ``(..., n) -> (...)``; ``+inf`` if an
    ``inf`` survives the trimming."""
    x = np.sort(np.asarray(x, dtype=np.float64), axis=-1)
    n = x.shape[-1]
    cut = int(0.25 * n)
    kept = x[..., cut : n - cut]
    with np.errstate(invalid="ignore"):
        return kept.mean(axis=-1)


def stratified_bootstrap(
    strata: Sequence[np.ndarray], statistic: Statistic, reps: int = 10_000, seed: int = 0
) -> np.ndarray:
    """``reps`` bootstrap replicates of ``statistic`` over the concatenated strata.

    Each replicate draws ``len(s)`` runs with replacement from every stratum ``s`` (e.g. the
    seeds of one task) and applies ``statistic`` (last-axis reducer) to their concatenation.
    Returns ``(reps,)``.
    """
    rng = np.random.default_rng(seed)
    parts = []
    for s in strata:
        s = np.asarray(s, dtype=np.float64)
        if s.size == 0:
            continue
        parts.append(s[rng.integers(0, s.size, size=(reps, s.size))])
    if not parts:
        return np.full(reps, np.nan)
    return statistic(np.concatenate(parts, axis=1))


def bootstrap_ci(
    strata: Sequence[np.ndarray] | np.ndarray,
    statistic: Statistic,
    confidence: float = 0.95,
    reps: int = 10_000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap interval ``(low, high)`` of ``statistic`` (rliable-style, stratified).

    ``strata`` is one array of runs or a list of arrays (one per task). The bounds are order
    statistics of the replicates (``method="lower"`` / ``"higher"``, i.e. no interpolation, exact
    with ``inf`` and never narrower than the interpolated interval).
    """
    if isinstance(strata, np.ndarray):
        strata = [strata]
    replicates = stratified_bootstrap(strata, statistic, reps, seed)
    alpha = (1.0 - confidence) / 2.0
    low = float(np.quantile(replicates, alpha, method="lower"))
    high = float(np.quantile(replicates, 1.0 - alpha, method="higher"))
    return low, high


def median_bounds(times: Sequence[float], stopped_at: Sequence[float]) -> tuple[float, float]:
    """The lowest and highest median of ``times`` together with runs cut short: ``(low, high)``.

    ``times``: finished runs' times to success (``+inf`` = unsolved at its limit), ``(n,)``;
    ``stopped_at``: runs stopped before their limit and unsolved so far, each known only to need at
    least this much interaction, ``(m,)``. The median of all ``n + m`` runs is lowest if every
    stopped run would have solved at once (its time = ``stopped_at``) and highest if none ever
    would (``+inf``); both bounds are attained, and both equal :func:`median` of ``times`` when
    ``m = 0``. NaN if there is no run at all.
    """
    finished = np.asarray(times, dtype=np.float64)
    cut = np.asarray(stopped_at, dtype=np.float64)
    if finished.size + cut.size == 0:
        return float("nan"), float("nan")
    low = float(median(np.concatenate([finished, cut])))
    high = float(median(np.concatenate([finished, np.full(cut.size, np.inf)])))
    return low, high


def times_with_failures(solved: Sequence[bool], times: Sequence[float | None]) -> np.ndarray:
    """Times to success with every unsolved run as ``+inf`` (never dropped); ``(n,)``."""
    out = np.array([t if ok and t is not None else np.inf for ok, t in zip(solved, times)], dtype=np.float64)
    return out


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval for a success rate, ``successes`` of ``n`` Bernoulli trials (e.g. test
    episodes), at the normal quantile ``z`` (default: 95 %), as fractions in ``[0, 1]``. Unlike
    ``p +- z sqrt(p(1-p)/n)`` it stays inside ``[0, 1]`` and does not collapse to a point at 0 or n."""
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"wilson_interval: {successes} successes of {n} trials (need 0 <= successes <= n, n >= 1)")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * float(np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def rate_interval(rate: float, n: int) -> tuple[float, float]:
    """:func:`wilson_interval` of a success rate measured over ``n`` episodes (``rate * n`` is a count)."""
    return wilson_interval(round(rate * n), n)
