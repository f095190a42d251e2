"""The benchmark's figures, as the radiation-search field reports them, per set and pooled.

Per policy, over a list of played episodes (:class:`EpisodeResult`; :func:`summarize`):

- **completion rate**: the share of episodes in which a detector came within 1.1 m of the source
  within the step limit, with a Wilson 95% interval;
- **median completed length**: the median number of moves of the completed episodes, with a
  distribution-free 95% interval from order statistics (:func:`median_ci`) and, as RAD-A2C prints
  them, the 2.5th and 97.5th percentiles of those lengths (a spread, not an interval of the median);
- **mean length**: the mean number of moves with a failure counted at the step limit, with a
  Student-t 95% interval (:func:`medc_training.stats.mean_ci`);
- **declaration**: how many episodes the team declared the source localised in (the declaration
  rule of :mod:`medc_training.envs.tl_estimate`: posterior mass >= 0.95 within 1.1 m of its most
  probable cell), the distance from the declared cell to the source (m) and the step of the
  declaration, over the episodes with one;
- **tracking error**: per episode the root-mean-square distance (m) from the team's posterior-mean
  source position to the source over the episode's steps (RAD-A2C's localization error is this
  for its own estimate), averaged over episodes with a 95% interval.

Two policies on the same episodes (the same set, the same count-noise seeds; :func:`paired`): the
per-episode difference in length (failures at the limit), its mean with a Student-t 95% interval
and its median, wins, losses and ties with an exact two-sided sign test, and how completions split.
Pairing removes the episodes' own spread from the comparison, which is what separates two policies
with few episodes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from medc_training.stats import mean_ci

__all__ = [
    "EpisodeResult",
    "median_ci",
    "paired",
    "scored_length",
    "sign_test",
    "summarize",
    "wilson",
]


@dataclass(frozen=True)
class EpisodeResult:
    """One played episode.

    set_id, index:     which episode of which set.
    length:            moves made (the step limit for a failure).
    success:           a detector came within the success radius of the source.
    declared_step:     the step (0 = at the first readings) of the team's first declaration while the
                       episode ran, None without one.
    declared_error_m:  distance from the declared cell to the source (m), None without a declaration.
    track_rmse_m:      root-mean-square distance (m) from the posterior-mean position to the source
                       over the steps the team estimated (before the finding move, for a success).
    """

    set_id: str
    index: int
    length: int
    success: bool
    declared_step: int | None = None
    declared_error_m: float | None = None
    track_rmse_m: float | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _finite(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def wilson(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score 95% interval (lo, hi) of a proportion; (nan, nan) for n = 0."""
    if n <= 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def _binom_cdf_half(k: int, n: int) -> float:
    """P(X <= k) for X ~ Binomial(n, 1/2), exactly (integers, then one division)."""
    if k < 0:
        return 0.0
    if k >= n:
        return 1.0
    total, term = 0, 1
    for i in range(k + 1):
        total += term
        term = term * (n - i) // (i + 1)
    return total / 2**n


def median_ci(values: Sequence[float], level: float = 0.95) -> tuple[float, float]:
    """Distribution-free interval of the median from order statistics: [x_(j), x_(n+1-j)] with the
    largest j such that 2 P(Binomial(n, 1/2) <= j - 1) <= 1 - ``level`` (coverage at least ``level``).
    (nan, nan) when no j qualifies (n <= 5 at 95%)."""
    xs = sorted(float(v) for v in values)
    n = len(xs)
    alpha = 1.0 - level
    j, below, term = 0, 0, 1  # below = 2**n P(X <= j), term = C(n, j)
    while j + 1 <= (n + 1) // 2:
        below += term
        if 2 * below / 2**n > alpha:
            break
        term = term * (n - j) // (j + 1)
        j += 1
    if j == 0:
        return math.nan, math.nan
    return xs[j - 1], xs[n - j]


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided sign-test p-value of ``wins`` against ``losses`` (ties left out)."""
    n = wins + losses
    if n == 0:
        return 1.0
    return min(1.0, 2.0 * _binom_cdf_half(min(wins, losses), n))


def scored_length(result: EpisodeResult, max_steps: int) -> float:
    """The length an episode counts for in every mean: its moves, or ``max_steps`` when it failed."""
    return float(result.length if result.success else max_steps)


def summarize(results: Iterable[EpisodeResult], max_steps: int) -> dict[str, Any]:
    """The field's figures over ``results`` (module docstring). Numbers that do not exist (a median
    of no completed episode, an interval of one value) are None."""
    rows = list(results)
    n = len(rows)
    done = sorted(r.length for r in rows if r.success)
    lengths = [scored_length(r, max_steps) for r in rows]
    mean, half = mean_ci(lengths)
    lo, hi = wilson(len(done), n)
    med_lo, med_hi = median_ci(done)
    declared = [r for r in rows if r.declared_step is not None]
    errors = [r.declared_error_m for r in declared]
    steps = [float(r.declared_step) for r in declared]
    tracks = [r.track_rmse_m for r in rows if r.track_rmse_m is not None]
    track_mean, track_half = mean_ci(tracks)
    out: dict[str, Any] = {
        "episodes": n,
        "completed": len(done),
        "completion_rate": len(done) / n if n else None,
        "completion_ci95": [_finite(lo), _finite(hi)],
        "median_completed_length": float(np.median(done)) if done else None,
        "median_ci95": [_finite(med_lo), _finite(med_hi)],
        "completed_p2_5": float(np.percentile(done, 2.5)) if done else None,
        "completed_p97_5": float(np.percentile(done, 97.5)) if done else None,
        "mean_length": _finite(mean),
        "mean_length_ci95": _finite(half),
        "declared": len(declared),
        "declared_rate": len(declared) / n if n else None,
        "declared_error_m_mean": float(np.mean(errors)) if errors else None,
        "declared_error_m_median": float(np.median(errors)) if errors else None,
        "declared_correct": sum(1 for e in errors if e <= 1.1 + 1e-9),
        "declared_step_mean": float(np.mean(steps)) if steps else None,
        "declared_step_median": float(np.median(steps)) if steps else None,
        "track_rmse_m_mean": _finite(track_mean),
        "track_rmse_m_ci95": _finite(track_half),
    }
    return out


def paired(a: Sequence[EpisodeResult], b: Sequence[EpisodeResult], max_steps: int) -> dict[str, Any]:
    """Policy A against policy B on the same episodes (``a[i]`` and ``b[i]`` the same set and index):
    per-episode length difference A - B (failures at ``max_steps``; negative = A shorter), its mean
    with a Student-t 95% interval, its median, A's wins / losses / ties with the sign test's p-value,
    and the completions split (both, only A, only B, neither). Raises ValueError when the episodes do
    not pair up."""
    if len(a) != len(b) or any((x.set_id, x.index) != (y.set_id, y.index) for x, y in zip(a, b)):
        raise ValueError("paired comparison needs the same episodes, in the same order, for both policies")

    diff = [scored_length(x, max_steps) - scored_length(y, max_steps) for x, y in zip(a, b)]
    mean, half = mean_ci(diff)
    wins = sum(1 for d in diff if d < 0)
    losses = sum(1 for d in diff if d > 0)
    return {
        "episodes": len(diff),
        "mean_diff": _finite(mean),
        "mean_diff_ci95": _finite(half),
        "median_diff": float(np.median(diff)) if diff else None,
        "wins": wins,
        "losses": losses,
        "ties": len(diff) - wins - losses,
        "sign_test_p": sign_test(wins, losses),
        "both_completed": sum(1 for x, y in zip(a, b) if x.success and y.success),
        "only_a_completed": sum(1 for x, y in zip(a, b) if x.success and not y.success),
        "only_b_completed": sum(1 for x, y in zip(a, b) if y.success and not x.success),
        "neither_completed": sum(1 for x, y in zip(a, b) if not x.success and not y.success),
    }
