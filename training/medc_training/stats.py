"""The statistics every figure, table and claim uses: means with Student-t 95% confidence intervals.

One module so that the report's bands (:func:`curve_band`), its tables and its claim verdicts
(:func:`mean_ci`, :func:`compare`) can never disagree on how a CI is computed. No scipy: the
two-sided 95% quantiles are tabulated, and the distributions the tests need are computed here.

The design every comparison has: the runs of a seed share that seed (its fixed evaluation
episodes and its seeding), so two methods are compared **paired by seed** (:func:`paired`: the
mean of the per-seed differences, its Student-t CI with df = n - 1, and on how many seeds each
side was ahead). The rest follows the test actually used:

- :func:`t_cdf` (Student t) and :func:`nct_cdf` (noncentral t) give p-values
  (:func:`t_pvalue`), the power of a two-sided t test at a true difference of ``delta`` standard
  errors (:func:`t_power`) and the difference it detects with a given power
  (:func:`detectable_delta`, in standard errors; times the test's standard error, in steps);
- :func:`non_inferiority` judges "at worst ``margin`` behind" by the CI's upper bound;
- :func:`censored_mean` counts a seed that never reaches a level at its budget (the mean is
  then a lower bound), so a speed-up is never averaged over the seeds that happened to reach it;
- :func:`holm` adjusts the p-values of a family of claims (Holm's step-down method).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: The two-sided level of every test and CI here.
ALPHA = 0.05

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


def percentile(values: Sequence[float], q: float) -> float:
    """The nearest-rank ``q``-th percentile (0-100) of ``values`` (not empty): the value at rank
    round(q / 100 * (n - 1)) of the sorted values, as latency reports give p50 and p99."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))]


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


def paired(a: Sequence[float], b: Sequence[float]) -> dict:
    """The paired comparison of ``a`` and ``b`` (``a[k]`` and ``b[k]`` measured on the same seed):
    {"n", "diff" (mean of a[k] - b[k]), "half" (Student-t 95% CI half-width, df = n - 1), "sd" (of
    the differences), "se", "t", "p" (two-sided), "a_lower" and "b_lower" (on how many seeds
    each side is the lower; ties count for neither)}. "half" and "p" are inf/nan below 2 pairs,
    and a zero spread gives p 0 (or 1 when every difference is 0)."""
    if len(a) != len(b):
        raise ValueError(f"paired samples of different sizes: {len(a)} and {len(b)}")
    d = [x - y for x, y in zip(a, b)]
    n = len(d)
    out = {"n": n, "a_lower": sum(x < 0 for x in d), "b_lower": sum(x > 0 for x in d)}
    if n == 0:
        return {**out, "diff": math.nan, "half": math.nan, "sd": math.nan, "se": math.nan, "t": math.nan,
                "p": math.nan}
    m = sum(d) / n
    if n < 2:
        return {**out, "diff": m, "half": math.inf, "sd": math.nan, "se": math.inf, "t": math.nan,
                "p": math.nan}
    sd = math.sqrt(sum((x - m) ** 2 for x in d) / (n - 1))
    se = sd / math.sqrt(n)
    t = m / se if se > 0 else (math.copysign(math.inf, m) if m else 0.0)
    return {**out, "diff": m, "half": t95(n - 1) * se, "sd": sd, "se": se, "t": t,
            "p": t_pvalue(t, n - 1)}


def welch(a: Sequence[float], b: Sequence[float]) -> dict:
    """:func:`compare` with what its test needs besides the CI: {"diff", "half", "se", "df" (the
    CI's df, min(n) - 1), "t", "p" (two-sided, on that df)}."""
    c = compare(list(a), list(b))
    df = min(len(a), len(b)) - 1
    if df < 1:
        return {**c, "se": math.inf, "df": df, "t": math.nan, "p": math.nan}
    se = c["half"] / t95(df)
    t = c["diff"] / se if se > 0 else (math.copysign(math.inf, c["diff"]) if c["diff"] else 0.0)
    return {**c, "se": se, "df": df, "t": t, "p": t_pvalue(t, df)}


def norm_cdf(x: float) -> float:
    """The standard normal CDF."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


def t_cdf(t: float, df: float) -> float:
    """The Student-t CDF with ``df`` degrees of freedom: for whole df the closed form in the
    angle theta = atan(t / sqrt(df)) (a finite sum of powers of cos theta), else :func:`nct_cdf`
    with no noncentrality."""
    if df <= 0:
        raise ValueError(f"df must be positive, got {df}")
    if math.isinf(t):
        return 1.0 if t > 0 else 0.0
    if df != int(df):
        return nct_cdf(t, df, 0.0)
    df = int(df)
    theta = math.atan(abs(t) / math.sqrt(df))
    c2 = math.cos(theta) ** 2
    if df % 2:  # odd: (2/pi)(theta + sin cos (1 + 2/3 c2 + 2*4/(3*5) c2^2 + ...))
        term, total = 1.0, 1.0 if df > 1 else 0.0
        for k in range(1, (df - 1) // 2):
            term *= c2 * (2 * k) / (2 * k + 1)
            total += term
        inside = 2.0 / math.pi * (theta + math.sin(theta) * math.cos(theta) * total)
    else:  # even: sin (1 + 1/2 c2 + 1*3/(2*4) c2^2 + ...)
        term, total = 1.0, 1.0
        for k in range(1, df // 2):
            term *= c2 * (2 * k - 1) / (2 * k)
            total += term
        inside = math.sin(theta) * total
    return 0.5 + math.copysign(0.5 * inside, t)


def t_pvalue(t: float, df: float) -> float:
    """Two-sided p-value of a t statistic."""
    if math.isnan(t):
        return math.nan
    return min(1.0, 2.0 * (1.0 - t_cdf(abs(t), df)))


def t_quantile(p: float, df: float) -> float:
    """The ``p`` quantile of the Student t with ``df`` degrees of freedom (bisection on
    :func:`t_cdf`, to 1e-10)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must lie in (0, 1), got {p}")
    if p < 0.5:
        return -t_quantile(1.0 - p, df)
    lo, hi = 0.0, 1.0
    while t_cdf(hi, df) < p:
        lo, hi = hi, hi * 2.0
    while hi - lo > 1e-10 * max(1.0, hi):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if t_cdf(mid, df) < p else (lo, mid)
    return 0.5 * (lo + hi)


#: Points of the integral over the chi variable in :func:`nct_cdf` (odd: Simpson's rule).
NCT_POINTS = 4001


def nct_cdf(t: float, df: float, delta: float) -> float:
    """The noncentral-t CDF: P(T <= t) for T = (Z + delta) / S, Z standard normal and S^2 a
    chi-square with ``df`` degrees of freedom over df. Computed as the expectation over S of
    Phi(t S - delta), by Simpson's rule over S's density where it is not negligible (the
    density's own integral on the same points normalises it)."""
    if df <= 0:
        raise ValueError(f"df must be positive, got {df}")
    spread = math.sqrt(2.0 / df)
    lo = math.sqrt(max(0.0, 1.0 - 14.0 * spread))
    hi = math.sqrt(1.0 + 14.0 * spread + 60.0 / df)
    s = np.linspace(lo, hi, NCT_POINTS)
    with np.errstate(divide="ignore"):
        log_s = np.where(s > 0, np.log(np.maximum(s, 1e-300)), -np.inf)
    log_density = (df - 1) * log_s - df * s * s / 2.0 if df != 1 else -s * s / 2.0
    density = np.exp(log_density - np.max(log_density))
    phi = np.array([norm_cdf(t * x - delta) for x in s])
    weights = np.ones(NCT_POINTS)
    weights[1:-1:2], weights[2:-1:2] = 4.0, 2.0
    return float(np.sum(weights * density * phi) / np.sum(weights * density))


def t_power(delta: float, df: float, alpha: float = ALPHA) -> float:
    """Power of the two-sided level-``alpha`` t test on ``df`` degrees of freedom when the true
    difference is ``delta`` standard errors (the noncentrality): P(|T| > t_{1-alpha/2}) under
    the noncentral t."""
    c = t_quantile(1.0 - alpha / 2.0, df)
    return 1.0 - nct_cdf(c, df, abs(delta)) + nct_cdf(-c, df, abs(delta))


def detectable_delta(df: float, power: float = 0.8, alpha: float = ALPHA) -> float:
    """The true difference, in standard errors, that the two-sided level-``alpha`` t test on
    ``df`` degrees of freedom detects with probability ``power`` (bisection on :func:`t_power`,
    to 1e-6); times the test's standard error it is the minimum detectable difference."""
    if not alpha < power < 1.0:
        raise ValueError(f"power must lie in (alpha, 1), got {power}")
    lo, hi = 0.0, 1.0
    while t_power(hi, df, alpha) < power:
        lo, hi = hi, hi * 2.0
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if t_power(mid, df, alpha) < power else (lo, mid)
    return 0.5 * (lo + hi)


def non_inferiority(diff: float, half: float, margin: float) -> str:
    """The claim "at worst ``margin`` behind" (``diff``: how far behind, higher = worse; ``half``:
    its CI's half-width) judged by the CI: "held" when the upper bound is within the margin,
    "did not hold" when the lower bound is beyond it, "inconclusive" otherwise (a mean within the
    margin whose upper bound is outside it is inconclusive)."""
    if math.isnan(diff) or math.isnan(half):
        return "not run"
    if diff + half <= margin:
        return "held"
    if diff - half > margin:
        return "did not hold"
    return "inconclusive"


def censored_mean(values: Sequence[float | None], budgets: Sequence[float]) -> tuple[float, int]:
    """(mean, how many were observed) of per-seed times to an event (``values[k]`` None: seed k
    never reached it within its budget ``budgets[k]``, counted at that budget). With a censored
    seed the mean is a lower bound on the mean time."""
    if len(values) != len(budgets):
        raise ValueError(f"{len(values)} values but {len(budgets)} budgets")
    if not values:
        return math.nan, 0
    counted = [b if v is None else v for v, b in zip(values, budgets)]
    return sum(counted) / len(counted), sum(v is not None for v in values)


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of a family's p-values, in the given order: the k-th smallest
    of m is multiplied by m - k + 1, the running maximum taken, capped at 1. A claim is resolved
    at the family-wise level alpha when its adjusted p-value is below alpha. nan stays nan and
    does not count in the family."""
    order = sorted((p, i) for i, p in enumerate(pvalues) if not math.isnan(p))
    m = len(order)
    out = [math.nan] * len(pvalues)
    running = 0.0
    for k, (p, i) in enumerate(order):
        running = max(running, min(1.0, (m - k) * p))
        out[i] = running
    return out
