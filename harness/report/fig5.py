"""Fig. 5 of ``harness report``: interaction time to success, one panel per task (log axis).

In each panel a row per learner (configuration): every seed a dot at its time to success, every
unsolved seed a ``>`` at the interaction it consumed (a lower bound), the median a bar; the paper's
and the literature's values in grey. Data first: ``fig5.csv`` holds every panel's points.
"""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from harness.report.figures import _plain_log_ticks, _plt
from harness.report.paper import PAPER_TABLE1
from harness.statistics import times_with_failures

#: the panels of Fig. 5, in order
FIG5_TASKS = ("cartpole", "dmc-cartpole", "double-pendulum", "unicycle")

#: a panel's title per task (other tasks: their name)
TASK_TITLES = {
    "cartpole": "cart-pole (cartpole)",
    "dmc-cartpole": "dm_control cart-pole (dmc-cartpole)",
    "double-pendulum": "double pendulum (double-pendulum)",
    "unicycle": "unicycle (unicycle)",
}

#: the task of a literature row without a ``task`` column (literature_fig5.csv is of cart-pole)
LITERATURE_TASK = "cartpole"

FIG5_FIELDS = ("task", "label", "kind", "runs", "solved", "median_s", "q25_s", "q75_s", "solved_min_s", "solved_max_s",
               "censored_at_s", "seed_times_s", "seed_interaction_s", "source")

PAPER_SOURCE = "Deisenroth & Rasmussen, ICML 2011, Table 1 (experience)"


def task_title(task: str) -> str:
    return TASK_TITLES.get(task, task)


def _row(task: str, label: str, kind: str, **values: Any) -> dict[str, Any]:
    """A row of ``fig5.csv`` with every field, in order (empty where ``values`` has none)."""
    return {field: values.get(field, "") for field in FIG5_FIELDS} | {"task": task, "label": label, "kind": kind}


def _grey_row(task: str, label: str, kind: str, low: float, high: float, source: str) -> dict[str, Any]:
    """A value (``low == high``) or a range from the paper or the literature."""
    return _row(task, label, kind, median_s=(low + high) / 2, q25_s=low, q75_s=high, solved_min_s=low,
                solved_max_s=high, censored_at_s=math.nan, source=source)


def paper_experience_s(task: str) -> tuple[float, float] | None:
    """The experience of the paper's Table 1 for ``task`` as ``(low, high)`` seconds (``"~ 60-90 s"``
    -> ``(60, 90)``); ``None`` for a task not in the paper."""
    if task not in PAPER_TABLE1:
        return None
    numbers = [float(n) for n in re.findall(r"\d+(?:\.\d+)?", PAPER_TABLE1[task][3])]
    return (min(numbers), max(numbers)) if numbers else None


def grey_rows(task: str, literature: Sequence[dict[str, str]]) -> list[dict[str, Any]]:
    """The paper's Table 1 experience for ``task`` (if it has one), then its literature rows (chronological)."""
    rows = []
    paper = paper_experience_s(task)
    if paper is not None:
        rows.append(_grey_row(task, "PILCO (paper, Table 1)", "paper", *paper, PAPER_SOURCE))
    of_task = [lit for lit in literature if (lit.get("task") or LITERATURE_TASK) == task]
    for lit in sorted(of_task, key=lambda r: (int(r.get("year") or 0), r["method"])):
        value = float(lit["interaction_seconds"])
        label = f"{lit['method']} ({lit.get('year', '')})".replace(" ()", "")
        rows.append(_grey_row(task, label, "literature", value, value, lit["source"]))
    return rows


def _seconds(values: Sequence[float]) -> str:
    return " ".join("inf" if math.isinf(t) else f"{t:.6g}" for t in values)


def ours_row(task: str, label: str, runs: Sequence[Any]) -> dict[str, Any]:
    """One learner we ran: median and quartiles of the time to success with unsolved runs as +inf
    (order statistics, no interpolation), the solved runs' min/max, the interaction at which the
    unsolved runs stopped (``censored_at_s``: their maximum), and per seed the time to success and
    the interaction consumed."""
    times = times_with_failures([r.solved for r in runs], [r.time_to_success for r in runs])
    solved = times[np.isfinite(times)]
    unsolved = [r.interaction_seconds for r in runs if not r.solved]
    return _row(
        task, label, "ours", runs=len(runs), solved=int(solved.size),
        median_s=float(np.median(times)),
        q25_s=float(np.quantile(times, 0.25, method="lower")),
        q75_s=float(np.quantile(times, 0.75, method="higher")),
        solved_min_s=float(solved.min()) if solved.size else math.nan,
        solved_max_s=float(solved.max()) if solved.size else math.nan,
        censored_at_s=max(unsolved) if unsolved else math.nan,
        seed_times_s=_seconds(times), seed_interaction_s=_seconds([r.interaction_seconds for r in runs]),
        source="this harness (MLflow runs: " + " ".join(r.run_id for r in runs) + ")",
    )


def fig5_data(by_task: dict[str, dict[str, Sequence[Any]]], literature: Sequence[dict[str, str]],
              tasks: Sequence[str] = FIG5_TASKS) -> list[dict[str, Any]]:
    """Rows of every panel, task by task: the paper's and literature's values, then one row per learner we ran."""
    rows: list[dict[str, Any]] = []
    for task in tasks:
        rows += grey_rows(task, literature)
        rows += [ours_row(task, label, runs) for label, runs in by_task.get(task, {}).items() if runs]
    return rows


# ---------------------------------------------------------------------------------------------
# drawing
# ---------------------------------------------------------------------------------------------


def _plain(seconds: float) -> str:
    """``15``, ``1.5``, ``1500``, ``20000``: never ``2e+04``."""
    return f"{seconds:.0f}" if seconds >= 100 else f"{seconds:.3g}"


def _median_text(row: dict[str, Any]) -> str:
    med = row["median_s"]
    if math.isfinite(med):
        return f"median {_plain(med)} s"
    censored = row["censored_at_s"]
    return f"median > {_plain(censored)} s" if isinstance(censored, float) and math.isfinite(censored) else "median not reached"


def _row_label(row: dict[str, Any]) -> str:
    name = textwrap.fill(str(row["label"]), 28)
    if row["kind"] != "ours":
        return name
    return f"{name}\n{row['solved']}/{row['runs']} solved, {_median_text(row)}"


def _draw_grey(ax, y: float, row: dict[str, Any]) -> None:
    """The paper's or a literature value in grey: a diamond, with a bar over its range if it has one."""
    low, high = row["solved_min_s"], row["solved_max_s"]
    if high > low:
        ax.plot([low, high], [y, y], color="0.6", lw=4, solid_capstyle="butt")
    ax.plot(row["median_s"], y, "D", color="0.5", ms=5)


def _draw_ours(ax, y: float, row: dict[str, Any]) -> None:
    """Seeds as dots (solved) and ``>`` at the interaction consumed (unsolved); the median as a bar."""
    times = [float(t) for t in str(row["seed_times_s"]).split()]
    used = [float(t) for t in str(row["seed_interaction_s"]).split()]
    jitter = np.linspace(-0.2, 0.2, len(times)) if len(times) > 1 else [0.0]
    for dy, t, u in zip(jitter, times, used):
        if math.isfinite(t):
            ax.plot(t, y + dy, "o", ms=3.5, color="k")
        else:
            ax.plot(u, y + dy, ">", ms=5, mfc="none", color="tab:red")
    if math.isfinite(row["median_s"]):
        ax.plot(row["median_s"], y, "|", ms=18, mew=2.5, color="tab:blue")


def _x_range(rows: Sequence[dict[str, Any]]) -> tuple[float, float]:
    values = [v for r in rows for v in (r["median_s"], r["solved_min_s"], r["solved_max_s"], r["censored_at_s"])
              if isinstance(v, float) and math.isfinite(v) and v > 0]
    values += [float(t) for r in rows for t in str(r["seed_interaction_s"]).split() if float(t) > 0]
    return (min(values) / 2, max(values) * 2) if values else (1.0, 100.0)


def fig5_panel(ax, task: str, rows: Sequence[dict[str, Any]]) -> None:
    """One task's panel: a line per row, top to bottom; ``no runs`` where no learner ran on it."""
    for y, row in enumerate(rows):
        (_draw_ours if row["kind"] == "ours" else _draw_grey)(ax, y, row)
    low, high = _x_range(rows)
    ax.set_xscale("log")
    ax.set_xlim(low, high)
    _plain_log_ticks(ax.xaxis, low, high)
    ax.set_ylim(max(len(rows), 1) - 0.5, -0.5)
    ax.set_yticks(range(len(rows)), [_row_label(r) for r in rows], fontsize=7)
    ax.set_title(task_title(task), fontsize=9)
    ax.grid(axis="x", which="major", alpha=0.3)
    if not any(r["kind"] == "ours" for r in rows):
        ax.text(0.99, 0.05, "no runs", transform=ax.transAxes, ha="right", va="bottom", fontsize=11, color="0.3")


def fig5_figure(rows: Sequence[dict[str, Any]], tasks: Sequence[str] = FIG5_TASKS):
    """A panel per task in ``tasks`` (:func:`fig5_panel`), stacked, each with its own log x axis; the open figure."""
    plt = _plt()
    of_task = {task: [r for r in rows if r["task"] == task] for task in tasks}
    heights = [0.45 * max(len(rs), 1) + 0.9 for rs in of_task.values()]
    fig, axes = plt.subplots(len(of_task), 1, figsize=(8.5, sum(heights) + 1.0), dpi=120, squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    for ax, (task, task_rows) in zip(axes[:, 0], of_task.items()):
        fig5_panel(ax, task, task_rows)
    axes[-1, 0].set_xlabel("interaction time to success [s] (log)")
    fig.suptitle("Data efficiency: interaction time to success per task (cf. ICML 2011 Fig. 5)", fontsize=10)
    fig.text(0.01, 0.005, "dots: seeds that solved; red >: unsolved seeds at the interaction they consumed (a lower bound); "
             "blue bar: median (unsolved = ∞)\ngrey: the paper's Table 1 experience and literature_fig5.csv, each with its source "
             "in fig5.csv", va="bottom", fontsize=6)
    fig.tight_layout(rect=(0, 0.4 / (sum(heights) + 1.0), 1, 1))
    return fig


def plot_fig5(rows: Sequence[dict[str, Any]], path: Path, tasks: Sequence[str] = FIG5_TASKS) -> Path:
    """:func:`fig5_figure` written to ``path``."""
    fig = fig5_figure(rows, tasks)
    fig.savefig(path)
    _plt().close(fig)
    return path
