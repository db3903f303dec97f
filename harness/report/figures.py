"""Figures of ``harness report``: learning curves, and what every figure draws with (Fig. 5: :mod:`~harness.report.fig5`).

Data first, plot second: every figure is drawn from a table that is also written as CSV, so the
numbers behind a picture can be checked without reading pixels.
"""

from __future__ import annotations

import textwrap
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: appended to a row label for the runs of that row stopped before their limit (curves, run tables)
STOPPED_SUFFIX = " (stopped)"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plain_log_ticks(axis, low: float, high: float) -> None:
    """Log-scale ticks written as plain numbers (``20``, ``0.5``) rather than ``2 x 10^1``;
    minor ticks labelled only when the axis spans less than about one decade."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    plain = FuncFormatter(lambda v, _: f"{v:g}")
    span = high / max(low, 1e-12)
    if 12 <= span < 1000:
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(plain)
    axis.set_minor_formatter(plain if span < 12 else NullFormatter())


# ---------------------------------------------------------------------------------------------
# learning curves
# ---------------------------------------------------------------------------------------------


def hold_on_grid(x: np.ndarray, y: np.ndarray, grid: np.ndarray, hold_after: bool = True) -> np.ndarray:
    """Zero-order hold of hand-over values on ``grid``: the value of the last hand-over at or
    before each grid point (the policy in hand), NaN before the first; after the last hand-over
    held (a run that ended at its limit or solved) or, with ``hold_after=False``, NaN (a run
    stopped before its limit: what it would have done next is unknown)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    out = np.full(grid.shape, np.nan)
    if x.size == 0:
        return out
    idx = np.searchsorted(x, grid, side="right") - 1
    ok = idx >= 0
    out[ok] = y[idx[ok]]
    if not hold_after:
        out[grid > x[-1]] = np.nan
    return out


def mean_band(values: np.ndarray, reps: int = 1000, seed: int = 0, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over runs (axis 0, NaN = run not yet evaluated) and a percentile-bootstrap band.

    ``values``: ``(runs, grid)``. Returns ``(mean, low, high)``, each ``(grid,)``.
    """
    rng = np.random.default_rng(seed)
    n = values.shape[0]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no run evaluated yet
        mean = np.nanmean(values, axis=0)
        draws = values[rng.integers(0, n, size=(reps, n))]  # (reps, n, grid)
        boot = np.nanmean(draws, axis=1)
        alpha = (1 - confidence) / 2
        low, high = np.nanquantile(boot, alpha, axis=0), np.nanquantile(boot, 1 - alpha, axis=0)
    return mean, low, high


def curve_table(curves: dict[str, list[dict[str, np.ndarray]]], points: int = 80,
                stopped: frozenset[str] = frozenset()) -> list[dict[str, Any]]:
    """Long table ``learner, interaction_s, runs_evaluated, {success,cost}_{mean,low,high}``.

    Per learner, a log-spaced grid from its first to 10 % past its last hand-over; every run is
    held constant after its last hand-over (a solved run keeps its solving policy), except the
    runs of the labels in ``stopped`` (runs stopped before their limit), which end there: the
    mean at a point is over the runs evaluated there (``runs_evaluated``). A learner without any
    evaluation (every run raised before its first hand-over) has no curve.
    """
    rows: list[dict[str, Any]] = []
    for label, histories in curves.items():
        histories = [h for h in histories if h["interaction_seconds"].size]
        if not histories:
            continue
        x_min = min(float(h["interaction_seconds"][0]) for h in histories)
        x_max = max(float(h["interaction_seconds"][-1]) for h in histories)
        # to 10 % past the last hand-over, so that the final values show as a step, not a point
        grid = np.unique(np.r_[np.geomspace(max(x_min, 1e-6), max(x_max, x_min, 1e-6), points), 1.1 * x_max])
        stats = {}
        for key, name in (("eval_success_rate", "success"), ("eval_cost", "cost")):
            values = np.stack([hold_on_grid(h["interaction_seconds"], h[key], grid, hold_after=label not in stopped)
                               for h in histories])
            stats[name] = mean_band(values)
            evaluated = np.sum(np.isfinite(values), axis=0)
        for j, x in enumerate(grid):
            rows.append({"learner": label, "interaction_s": float(x), "runs_evaluated": int(evaluated[j]),
                         **{f"{name}_{part}": float(stats[name][k][j]) for name in ("success", "cost") for k, part in enumerate(("mean", "low", "high"))}})
    return rows


def plot_curves(rows: Sequence[dict[str, Any]], path: Path, task: str,
                per_run: dict[str, list[dict[str, np.ndarray]]] | None = None) -> Path:
    """Two panels (success rate, cost) vs interaction seconds (log), one line + band per learner;
    with ``per_run`` (label -> run histories, see :func:`harness.report.history`), every run's
    hand-overs as a thin line in the learner's colour."""
    plt = _plt()
    labels = list(dict.fromkeys(r["learner"] for r in rows))
    # the legend goes under both panels (row labels can be long), one entry per line
    legend_in = 0.2 * len(labels) + 0.25 if labels else 0.0
    height = 4.2 + legend_in
    fig, axes = plt.subplots(1, 2, figsize=(10, height), dpi=120)
    for label in labels:
        sub = [r for r in rows if r["learner"] == label]
        x = np.array([r["interaction_s"] for r in sub])
        for ax, name, key in zip(axes, ("success", "cost"), ("eval_success_rate", "eval_cost")):
            mean = np.array([r[f"{name}_mean"] for r in sub])
            line, = ax.step(x, mean, where="post", label=f"{label} (n={max(r['runs_evaluated'] for r in sub)})")
            ax.fill_between(x, [r[f"{name}_low"] for r in sub], [r[f"{name}_high"] for r in sub], step="post", color=line.get_color(), alpha=0.2)
            if label.endswith(STOPPED_SUFFIX):
                line.set_linestyle("--")
            for h in (per_run or {}).get(label, []):
                if h["interaction_seconds"].size:
                    ax.step(h["interaction_seconds"], h[key], where="post", color=line.get_color(), lw=0.6, alpha=0.35,
                            ls=line.get_linestyle())
    axes[0].set(ylabel="evaluation success rate", ylim=(-0.03, 1.03))
    axes[1].set(ylabel="evaluation cost (sum over the episode)")
    xs = [r["interaction_s"] for r in rows] or [1.0]
    for ax in axes:
        ax.set_xscale("log")
        _plain_log_ticks(ax.xaxis, min(xs), max(xs))
        ax.set_xlabel("interaction [s] (log)")
    if labels:
        handles, names = axes[0].get_legend_handles_labels()
        fig.legend(handles, names, fontsize=7, loc="lower center", ncol=1, frameon=False)
    else:
        axes[0].text(0.5, 0.5, "no evaluations logged", transform=axes[0].transAxes, ha="center")
    stopped_note = f"; dashed '{STOPPED_SUFFIX.strip()}' = runs stopped before their limit, not counted, ending where they stopped" \
        if any(label.endswith(STOPPED_SUFFIX) for label in labels) else ""
    title = (f"{task}: mean over seeds with 95 % bootstrap band, thin lines = single runs (policy in hand held between "
             f"hand-overs){stopped_note}")
    fig.suptitle(textwrap.fill(title, 140), fontsize=8)
    fig.tight_layout(rect=(0, legend_in / height, 1, 1))
    fig.savefig(path)
    plt.close(fig)
    return path
