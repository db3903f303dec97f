"""How the report writes numbers: ranges, statistics with their CIs, bounds, and CSV files."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def value_range(values: Sequence[float]) -> tuple[float, float, float]:
    if not values:
        return (math.nan, math.nan, math.nan)
    arr = np.asarray(values, dtype=np.float64)
    return float(np.median(arr)), float(arr.min()), float(arr.max())



def fmt_seconds(value: float) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if math.isinf(value):
        return "∞"
    return f"{value:.1f}"


def fmt_stat(point: float, low: float, high: float) -> str:
    if math.isnan(point):
        return "–"
    if math.isinf(point):
        return f"not reached [{fmt_seconds(low)}, {fmt_seconds(high)}]"
    return f"{point:.1f} [{fmt_seconds(low)}, {fmt_seconds(high)}]"


def fmt_bounds(low: float, high: float, stopped: int, finished: int) -> str:
    """``'≥ 63.0 (2 stopped of 4)'``, ``'40.0–55.0 (…)'``, or ``'–'`` without stopped runs."""
    if not stopped:
        return "–"
    runs = f"({stopped} stopped of {stopped + finished})"
    if low == high:
        return f"{fmt_seconds(low)} {runs}"
    return f"≥ {fmt_seconds(low)} {runs}" if math.isinf(high) else f"{fmt_seconds(low)}–{fmt_seconds(high)} {runs}"


def fmt_number(value: float) -> str:
    """Integers as such (``305``), other numbers with one decimal (``1.5``)."""
    return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"


def fmt_decimal(value: float) -> str:
    return f"{value:.1f}"


def fmt_range(med: float, lo: float, hi: float, fmt=fmt_number) -> str:
    if math.isnan(med):
        return "–"
    return f"{fmt(med)} [{fmt(lo)}–{fmt(hi)}]"



def write_csv(path: Path, rows: Sequence[dict[str, Any]], fields: Sequence[str] | None = None) -> Path:
    """``rows`` as CSV (``inf``/``nan`` written as such); a header only if there are no rows."""
    fieldnames = list(rows[0]) if rows else list(fields or [])
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fieldnames)
        writer.writeheader()
        writer.writerows(rows)
    return path
