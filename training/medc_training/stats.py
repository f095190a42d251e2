"""The statistics every figure, table and claim uses: means with Student-t 95% confidence intervals.

One module so that the report's bands (:func:`curve_band`), its tables and its claim verdicts
(:func:`mean_ci`, :func:`compare`) can never disagree on how a CI is computed. No scipy: the
two-sided 95% quantiles are tabulated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

# Two-sided 95% Student-t quantiles by degrees of freedom (no scipy dependency).
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262,
       10: 2.228, 15: 2.131, 20: 2.086, 30: 2.042}


def t95(df: int) -> float:
    """Two-sided 95% Student-t quantile for ``df`` degrees of freedom (the tabulated df at or
    below it, 1.96 past 30; inf for df <= 0)."""
    if df <= 0:
        return math.inf
    keys = sorted(k for k in T95 if k <= df)
    return T95[keys[-1]] if df <= 30 else 1.96


def mean_ci(values: list[float]) -> tuple[float, float]:
    """(mean, half-width of the Student-t 95% CI); half-width inf for one value, nan for none."""
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    m = sum(values) / n
    if n < 2:
        return m, math.inf
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (n - 1))
    return m, t95(n - 1) * sd / math.sqrt(n)


def compare(a: list[float], b: list[float]) -> dict:
    """Welch-style difference of means (a - b) with a 95% CI."""
    ma, _ = mean_ci(a)
    mb, _ = mean_ci(b)
    if len(a) < 2 or len(b) < 2:
        return {"diff": ma - mb, "half": math.inf}
    va = sum((x - ma) ** 2 for x in a) / (len(a) - 1)
    vb = sum((x - mb) ** 2 for x in b) / (len(b) - 1)
    se = math.sqrt(va / len(a) + vb / len(b))
    df = min(len(a), len(b)) - 1
    return {"diff": ma - mb, "half": t95(df) * se}


def curve_band(curves: Sequence[Sequence[float]]) -> tuple[np.ndarray, np.ndarray]:
    """Per-point mean over seeds and half-width of the Student-t 95% CI (0 with one seed)."""
    arr = np.asarray(curves, dtype=float)
    mean = np.nanmean(arr, axis=0)
    n = arr.shape[0]
    if n < 2:
        return mean, np.zeros_like(mean)
    return mean, t95(n - 1) * np.nanstd(arr, axis=0, ddof=1) / math.sqrt(n)


def learning_score(curve: Sequence[float]) -> float:
    """Mean evaluation episode length over a run's evaluations after step 0 (the area under the
    learning curve over its length): lower is better, rewarding both faster and better learning."""
    return float(sum(curve[1:]) / max(1, len(curve) - 1)) if len(curve) > 1 else float(curve[0])
