"""Statistics of repeated timings and the Pareto choices of the accuracy report.

- ``summary(values)``: median, quartiles, min, max and count of repeated measurements;
- ``best_within(rows, budget)``: the most accurate row whose cost fits a budget;
- ``budget_table(rows, budgets)``: that choice for each of several budgets;
- ``pareto_front(rows)``: the rows no other row beats on both cost and accuracy.

Rows are dicts; the cost and value keys are parameters (``seconds``/``psnr`` by default).
Ties (equal values, or values within ``tie``): the cheaper row wins, then the earlier one.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def summary(values: Sequence[float]) -> dict:
    """{'median', 'p25', 'p75', 'min', 'max', 'n'} of the finite ``values`` (numpy's linear percentiles)."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"median": math.nan, "p25": math.nan, "p75": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    p25, median, p75 = np.percentile(v, [25, 50, 75])
    return {"median": float(median), "p25": float(p25), "p75": float(p75), "min": float(v.min()), "max": float(v.max()), "n": int(v.size)}


def format_spread(s: dict, scale: float = 1.0, digits: int = 1) -> str:
    """``'12.3 (11.9-13.0)'``: the median and the interquartile range, times ``scale``
    (``'0.4 (-1.2 to 2.0)'`` when the range holds a negative number)."""
    if not s["n"]:
        return "-"
    lo, hi = s["p25"] * scale, s["p75"] * scale
    dash = " to " if lo < 0 or hi < 0 else "-"
    return f"{s['median'] * scale:.{digits}f} ({lo:.{digits}f}{dash}{hi:.{digits}f})"


def _finite(row, key) -> bool:
    value = row.get(key)
    return value is not None and math.isfinite(value)


def best_within(rows: Sequence[dict], budget: float, cost: str = "seconds", value: str = "psnr", tie: float = 0.0):
    """The row with the highest ``value`` among those with ``cost <= budget`` (None when none fits).

    Rows within ``tie`` of the highest value count as equally good: of those the
    cheapest wins, then the earliest.
    """
    fitting = [row for row in rows if _finite(row, cost) and _finite(row, value) and row[cost] <= budget]
    if not fitting:
        return None
    top = max(row[value] for row in fitting)
    best = None
    for row in fitting:
        if row[value] >= top - tie and (best is None or row[cost] < best[cost]):
            best = row
    return best


def budget_table(rows: Sequence[dict], budgets: Sequence[float], cost: str = "seconds", value: str = "psnr", tie: float = 0.0) -> list:
    """[(budget, best row or None)] for each budget, in the order given (``tie`` as in ``best_within``)."""
    return [(budget, best_within(rows, budget, cost, value, tie)) for budget in budgets]


def pareto_front(rows: Sequence[dict], cost: str = "seconds", value: str = "psnr") -> list:
    """The rows not dominated by another (one at most as costly and more accurate, or cheaper and as accurate), by cost."""
    ranked = sorted((r for r in rows if _finite(r, cost) and _finite(r, value)), key=lambda r: (r[cost], -r[value]))
    front, top = [], -math.inf
    for row in ranked:
        if row[value] > top:
            front.append(row)
            top = row[value]
    return front
