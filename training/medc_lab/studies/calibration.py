"""Whether the team's declarations are right as often as they claim: a reliability study of the
declaration rule (:mod:`medc_training.envs.tl_estimate`).

A declaration at threshold p says "a UAV flown to this cell finds the source with probability
>= p". Over fixed, seeded episodes (:func:`medc_training.declaration_eval.threshold_episodes`: the
episodes and the play of :mod:`medc_training.declaration_eval`, every threshold of
:data:`THRESHOLDS` checked on the same play) this module counts, per threshold, the declarations
and the right ones, with a Wilson 95 % interval on the right rate; and the reliability curve: the
declarations of the lowest threshold (one per episode that declares) grouped by the mass they were
declared at (:data:`MASS_BINS`), the right rate of each group against its mean mass. A rule is
calibrated at p when the right rate of its declarations is at least p; the study flags a threshold
whose interval lies wholly below it. It also tallies every step's verdict (the mass at the MAP cell
and whether the source is within the radius of it, declared or not) in the same bins.

``python -m medc_lab.cli.calibrate CONTROLLER_OR_BUNDLE --sensing realistic --grid 20`` prints
the tables and writes one JSON record per configuration (``--out``). The probe options change one
part of the model at a time: ``--levels NS,NB`` the estimator's strength and background levels (the
simulator still draws both from the preset's continuous ranges), ``--strength LO,HI`` and
``--background LO,HI`` the ranges (simulator and estimator), ``--line`` the line-of-sight rule
(both), ``--success-radius`` the radius a declaration claims the source within and is judged by.
"""

from __future__ import annotations

from itertools import pairwise

import torch
from medc_training.radbench.results import wilson as proportion_interval

#: The thresholds the study checks, in one play.
THRESHOLDS = (0.5, 0.8, 0.9, 0.95, 0.99, 0.999)
#: Edges of the declared-mass groups of the reliability curve (the last group includes 1).
MASS_BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 0.999, 1.0)


def wilson(right: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval (95 % for the default z) of a right rate of ``right`` in ``n``
    (:func:`medc_training.radbench.results.wilson`); (0, 1) when n = 0: with nothing declared,
    any rate is possible."""
    return (0.0, 1.0) if n == 0 else proportion_interval(right, n, z)


def _group(masses: list[float], rights: list[bool]) -> list[dict]:
    """Rows of the reliability curve: per :data:`MASS_BINS` group, the count, the right count and
    rate, its Wilson interval and the mean mass."""
    out = []
    for lo, hi in pairwise(MASS_BINS):
        last = hi == MASS_BINS[-1]
        picked = [(m, ok) for m, ok in zip(masses, rights) if lo <= m and (m < hi or last)]
        n, right = len(picked), sum(1 for _, ok in picked if ok)
        out.append({"bin": [lo, hi], "n": n, "right": right, "rate": right / n if n else None,
                    "wilson": list(wilson(right, n)),
                    "mean_mass": sum(m for m, _ in picked) / n if n else None})
    return out


def reliability(rows: list[dict], thresholds: tuple[float, ...] = THRESHOLDS,
                step_masses: list | None = None) -> dict:
    """The study's tables from :func:`~medc_training.declaration_eval.threshold_episodes`' rows:
    ``thresholds`` (per threshold: declared, right, rate, Wilson interval, mean mass and step of its
    declarations, ``calibrated`` = the interval's upper bound >= the threshold), ``curve`` (the
    lowest threshold's declarations by declared mass) and, when ``step_masses`` is given,
    ``steps`` (every step's verdict in the same groups)."""
    per = []
    for k, threshold in enumerate(thresholds):
        marks = [row["declarations"][k] for row in rows if row["declarations"][k] is not None]
        n, right = len(marks), sum(1 for m in marks if m["correct"])
        lo, hi = wilson(right, n)
        per.append({"threshold": threshold, "declared": n, "right": right, "rate": right / n if n else None,
                    "wilson": [lo, hi], "calibrated": hi >= threshold,
                    "mean_mass": sum(m["mass"] for m in marks) / n if n else None,
                    "mean_step": sum(m["step"] for m in marks) / n if n else None})
    first = [row["declarations"][0] for row in rows if row["declarations"][0] is not None]
    out = {"episodes": len(rows), "thresholds": per,
           "curve": _group([m["mass"] for m in first], [m["correct"] for m in first])}
    if step_masses is not None and step_masses:
        mass = torch.cat([m for m, _ in step_masses]).tolist()
        right = torch.cat([r for _, r in step_masses]).tolist()
        out["steps"] = _group(mass, right)
    return out


def format_tables(study: dict) -> str:
    """The study as plain-text tables."""
    lines = ["threshold  declared  right  rate    wilson95          mean mass  mean step"]
    for t in study["thresholds"]:
        rate = "   -  " if t["rate"] is None else f"{t['rate']:.4f}"
        mm = "   -  " if t["mean_mass"] is None else f"{t['mean_mass']:.4f}"
        ms = "  -" if t["mean_step"] is None else f"{t['mean_step']:.2f}"
        flag = "" if t["calibrated"] else "  BELOW"
        lines.append(f"{t['threshold']:<9}  {t['declared']:>8}  {t['right']:>5}  {rate}  "
                     f"[{t['wilson'][0]:.4f}, {t['wilson'][1]:.4f}]  {mm}     {ms}{flag}")
    for key, title in (("curve", "declared mass (first declaration)"), ("steps", "every step's MAP mass")):
        if key not in study:
            continue
        lines.append(f"{title:<34}  n      right  rate    wilson95          mean mass")
        for g in study[key]:
            rate = "   -  " if g["rate"] is None else f"{g['rate']:.4f}"
            mm = "   -  " if g["mean_mass"] is None else f"{g['mean_mass']:.4f}"
            lines.append(f"[{g['bin'][0]}, {g['bin'][1]}{']' if g['bin'][1] == 1.0 else ')':<1}"
                         f"{'':<{34 - len(str(g['bin'][0])) - len(str(g['bin'][1])) - 4}}  {g['n']:>6} "
                         f"{g['right']:>6}  {rate}  [{g['wilson'][0]:.4f}, {g['wilson'][1]:.4f}]  {mm}")
    return "\n".join(lines)
