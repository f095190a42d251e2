"""The yardsticks a report of the claims protocol puts beside its learned teams.

- **Reference lines**: random moves and the classical controllers (:mod:`medc_training.controllers`)
  on fixed episodes of the regime, as :mod:`medc_lab.studies.regime_probes` writes them
  (``<folder>/<regime>/<policy>.json``).
- **Final policy against the best controller**, as the claims protocol fixed it: a run's final level
  per seed against the best controller's mean episode length on the reference episodes, the
  difference with a 95% CI combining the seeds' (Student t) and the controller's episodes'
  half-widths (:func:`versus_reference`); and, added after the protocol, on the same episodes
  (:func:`versus_best`): per seed, a run's final level (the mean of its last three evaluations,
  each on the seed's fixed evaluation episodes) minus a classical controller's mean episode length
  on those same episodes (as :func:`.reference_play.controller_play` plays them); the mean of these paired
  differences over the seeds with a 95% Student-t CI, against the controller with the lowest mean
  length on them.
- **Steps to sparse's final level**: the training steps at which a run's evaluation first reaches
  MDRL-sparse's final level (the mean over sparse's seeds of their last three evaluations), as a
  ratio to the steps sparse itself needs.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from medc_training.stats import mean_ci

#: The controllers a user would pick instead of a learned team (random play is a reference line,
#: not a controller to beat).
CONTROLLERS = ("gradient", "greedy", "infotaxis")
#: Evaluations averaged into a run's final level.
FINAL_EVALS = 3


def regime_name(grid: int, walls: int, max_steps: int) -> str:
    """The regime's folder name, as :mod:`medc_lab.studies.regime_probes` names it (g40w2t50)."""
    return f"g{grid}w{walls}t{max_steps}"


def load_references(folder: Path) -> dict[str, dict]:
    """{policy: {"length", "length_ci", "success", "episodes"}} for every ``<policy>.json`` in
    ``folder`` (empty when there is none)."""
    refs = {}
    for path in sorted(folder.glob("*.json")):
        record = json.loads(path.read_text())
        length, half = mean_ci([float(x) for x in record["lengths"]])
        success, _ = mean_ci([float(x) for x in record["successes"]])
        refs[record["policy"]] = {"length": length, "length_ci": half, "success": success,
                                  "episodes": len(record["lengths"])}
    return refs


def reference_text(refs: dict[str, dict]) -> str:
    """One line naming every reference policy's mean episode length ± CI and success rate."""
    episodes = sorted({r["episodes"] for r in refs.values()})
    cells = [f"{name} {r['length']:.1f} ± {r['length_ci']:.1f} steps ({r['success']:.0%} found)"
             for name, r in sorted(refs.items(), key=lambda kv: kv[1]["length"])]
    return (f"- **Reference lines** ({'/'.join(map(str, episodes))} fixed episodes each, played to their "
            f"end): " + "; ".join(cells))


def final_level(curve: Sequence[float]) -> float:
    """A run's final level: the mean of its last FINAL_EVALS evaluations."""
    tail = list(curve[-FINAL_EVALS:])
    return sum(tail) / len(tail)


def _verdict(diff: float, half: float) -> str:
    if diff + half < 0:
        return "beats"
    if diff - half > 0:
        return "does not beat"
    return "not resolved against"


def versus_reference(label: str, curves: Sequence[Sequence[float]], refs: dict[str, dict]) -> str | None:
    """The claims protocol's comparison: ``label``'s final level (one curve per seed) against the
    best classical controller in ``refs`` (its mean over the reference episodes), the difference
    with a CI combining the seeds' and the episodes' half-widths; None when no controller was played."""
    played = {k: v for k, v in refs.items() if k in CONTROLLERS}
    if not played or not curves:
        return None
    name, best = min(played.items(), key=lambda kv: kv[1]["length"])
    m, h = mean_ci([final_level(c) for c in curves])
    diff = m - best["length"]
    half = math.sqrt(h * h + best["length_ci"] ** 2) if math.isfinite(h) else math.inf
    return (f"{label}: final {m:.2f} ± {h:.2f} steps, {_verdict(diff, half)} {name} ({best['length']:.2f} ± "
            f"{best['length_ci']:.2f}): {diff:+.2f} ± {half:.2f} (n = {len(curves)} seeds)")


def versus_best(label: str, curves: Sequence[Sequence[float]],
                played: Sequence[dict[str, float]] | None) -> str | None:
    """How ``label``'s final policies (one curve per seed) compare with the best classical
    controller on the same episodes; ``played[k]``: each controller's mean episode length on the
    evaluation episodes of seed k (those of ``curves[k]``). Per seed, the difference of the final
    level and the controller's length; its mean over the seeds with a 95% Student-t CI, against the
    controller (of CONTROLLERS, played on every seed) with the lowest mean length over the seeds.
    None when no controller was played."""
    if not curves or not played:
        return None
    if len(played) != len(curves):
        raise ValueError(f"{label}: {len(curves)} curves but controller lengths of {len(played)} seeds")
    names = [n for n in CONTROLLERS if all(n in p for p in played)]
    if not names:
        return None
    name = min(names, key=lambda n: sum(p[n] for p in played))
    finals = [final_level(c) for c in curves]
    m, h = mean_ci(finals)
    cm, ch = mean_ci([p[name] for p in played])
    diff, half = mean_ci([f - p[name] for f, p in zip(finals, played, strict=True)])
    return (f"{label}: final {m:.2f} ± {h:.2f} steps, {_verdict(diff, half)} {name} ({cm:.2f} ± {ch:.2f} "
            f"on the same episodes): {diff:+.2f} ± {half:.2f} (n = {len(curves)} seeds)")


def steps_to_level(steps: Sequence[float], curve: Sequence[float], level: float) -> float | None:
    """The first evaluation step at which ``curve`` is at or below ``level`` (None: never)."""
    for step, value in zip(steps, curve):
        if value <= level:
            return float(step)
    return None


def _reached(steps: Sequence[float], curves: Sequence[Sequence[float]], level: float) -> list[float]:
    """The steps at which each curve first reaches ``level``, for the curves that do."""
    return [s for s in (steps_to_level(steps, c, level) for c in curves) if s is not None]


def speed_line(label: str, steps: Sequence[float], curves: Sequence[Sequence[float]], level: float,
               sparse_steps: float | None) -> str:
    """``label``'s mean steps to reach ``level`` over the seeds that reach it, and the ratio to
    sparse's own (``sparse_steps``)."""
    reached = _reached(steps, curves, level)
    if not reached:
        return f"{label}: never within the budget (0 of {len(curves)} seeds)"
    mean = sum(reached) / len(reached)
    ratio = f", ratio to sparse {mean / sparse_steps:.2f}" if sparse_steps else ""
    return f"{label}: {mean:,.0f} steps ({len(reached)} of {len(curves)} seeds){ratio}"


def speed_section(data: dict, sparse_label: str) -> str | None:
    """The steps-to-sparse's-final-level line of a panel (``data``: label -> (steps, curves, ...));
    None without a sparse series."""
    if sparse_label not in data:
        return None
    s_steps, s_curves = data[sparse_label][0], data[sparse_label][1]
    level = sum(final_level(c) for c in s_curves) / len(s_curves)
    reached = _reached(s_steps, s_curves, level)
    sparse_steps = sum(reached) / len(reached) if reached else None
    lines = [speed_line(label, v[0], v[1], level, sparse_steps) for label, v in data.items()]
    return (f"- **Steps to reach MDRL-sparse's final level** ({level:.2f} steps per episode; mean over "
            "the seeds that reach it): " + "; ".join(lines))
