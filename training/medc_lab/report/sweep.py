"""The when-do-experts-help sweep's section of the claims report (docs/reproduction/claims/SWEEP.md).

Each cell is MEDC with the six users' experts at one area (grid side), R_E and Q, measured against
MDRL-sparse at the same area on the sweep's seeds:

- **Speed-up**: the training steps sparse needs to reach L_G divided by the steps MEDC needs, L_G
  being sparse's final level at that area (the mean over its seeds of the mean of its last three
  evaluations) and a run's steps the mean over its seeds of its first evaluation at or below L_G. A
  seed that never reaches L_G counts its whole budget, which makes its side's mean a lower bound:
  the speed-up is then at least (sparse's side, "≥") or at most (MEDC's side, "≤") the ratio shown,
  and bounded neither way when both sides count one ("?").
- **Learning-score difference** MEDC − sparse (the protocol's metric), difference of means with a
  Welch 95% CI (:func:`medc_training.stats.compare`); "under-powered" when the half-width exceeds
  what 3 seeds resolve (SWEEP_UNDERPOWERED).
- **Guided share**: the share of training agent-steps in expert-guided episodes, and the share of
  those on which the expert's move was taken (the follow rate), from the run's metrics.csv.
- **Reward rarity**: random valid moves' success rate on the learnability gate's episodes of the area.

Hypotheses H1–H3 are answered "supported", "not supported" or "not resolved" from the CIs, as the
amendment states them. The section reads the runs through the report being built
(:class:`.build.Report`, passed in); it adds no claim to the report's verdict counts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from medc_training.stats import compare, learning_score

from ..catalogue import SWEEP_GRIDS, SWEEP_PROTOCOL, SWEEP_QS, SWEEP_RATES, SWEEP_UNDERPOWERED
from ..figures import SweepCell
from .references import final_level, steps_to_level

#: The heat map written next to the report.
HEATMAP = "sweep.png"


@dataclass(frozen=True)
class Arm:
    """One run's finished seeds as the sweep reads them: per seed, the evaluation steps and
    curve, the training budget and the guided share and follow rate (:func:`guided_share`)."""

    steps: tuple[tuple[float, ...], ...]
    curves: tuple[tuple[float, ...], ...]
    budgets: tuple[float, ...]
    guided: tuple[float, ...]
    follow: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.curves)

    def scores(self) -> list[float]:
        return [learning_score(c) for c in self.curves]

    def steps_to(self, level: float) -> tuple[float, int]:
        """The mean over seeds of the steps of the first evaluation at or below ``level`` (a seed
        that never reaches it counts its budget), and how many seeds reached it."""
        reached = [steps_to_level(s, c, level) for s, c in zip(self.steps, self.curves)]
        counted = [b if s is None else s for s, b in zip(reached, self.budgets)]
        return sum(counted) / len(counted), sum(s is not None for s in reached)


def guided_share(rows: Sequence[dict]) -> tuple[float, float]:
    """(guided share, follow rate) of one seed's metrics rows. A row's ``expert_step_fraction`` is
    the share of the training steps since the previous row taken in expert-guided episodes, so the
    run's share is their mean weighted by the steps each row covers (every update counts alike);
    its ``expert_follow_rate`` is the share of the row's guided agent-steps on which the expert's
    move was taken, so the run's is weighted by the guided steps. The row at step 0 (before any
    training) and rows without the column count nothing; nan when no row counts."""
    share = share_steps = taken = guided = 0.0
    previous = 0.0
    for row in rows:
        span, previous = row["step"] - previous, row["step"]
        fraction = row.get("expert_step_fraction", math.nan)
        if span <= 0 or math.isnan(fraction):
            continue
        share, share_steps = share + fraction * span, share_steps + span
        follow = row.get("expert_follow_rate", math.nan)
        if not math.isnan(follow):
            taken, guided = taken + follow * fraction * span, guided + fraction * span
    return (share / share_steps if share_steps else math.nan, taken / guided if guided else math.nan)


def read_arm(seeds: Sequence[tuple[dict, list[dict]]]) -> Arm | None:
    """The :class:`Arm` of a run's (summary, metrics rows) per seed; None when no seed finished."""
    seeds = [(summary, rows) for summary, rows in seeds if rows]
    if not seeds:
        return None
    shares = [guided_share(rows) for _, rows in seeds]
    return Arm(steps=tuple(tuple(r["step"] for r in rows) for _, rows in seeds),
               curves=tuple(tuple(r["episode_length"] for r in rows) for _, rows in seeds),
               budgets=tuple(float(s["config"]["total_steps"]) for s, _ in seeds),
               guided=tuple(g for g, _ in shares), follow=tuple(f for _, f in shares))


@dataclass(frozen=True)
class Speedup:
    """Sparse's steps to L_G over MEDC's; ``bound``: "" exact, "≥" / "≤" a lower / upper bound
    (sparse's / MEDC's side counts a seed's whole budget), "?" bounded neither way (both do)."""

    value: float
    bound: str = ""

    @classmethod
    def of(cls, sparse_steps: float, sparse_all: bool, medc_steps: float, medc_all: bool) -> Speedup:
        """From both sides' mean steps and whether all their seeds reached L_G."""
        if medc_steps > 0:
            value = sparse_steps / medc_steps
        else:
            value = math.inf if sparse_steps > 0 else math.nan
        bound = {(True, True): "", (False, True): "≥", (True, False): "≤"}.get((sparse_all, medc_all), "?")
        return cls(value, bound)

    def text(self) -> str:
        return f"{self.bound}{self.value:.2f}×"


@dataclass(frozen=True)
class Area:
    """MDRL-sparse at one area: its seeds, final level L_G, steps to L_G (and how many of its seeds
    reached it), learnability gate (:meth:`.judge.Judge.gate_result`) and random play's success
    rate on the gate's episodes."""

    grid: int
    sparse: str
    arm: Arm | None
    gate: dict
    random_success: float

    @property
    def level(self) -> float:
        return sum(final_level(c) for c in self.arm.curves) / self.arm.n

    @property
    def testable(self) -> bool:
        return bool(self.gate.get("passed"))

    @property
    def name(self) -> str:
        return f"{self.grid}×{self.grid}"


@dataclass(frozen=True)
class CellResult:
    """One cell's measures against its area's sparse (``arm`` None: not run)."""

    cell: SweepCell
    arm: Arm | None
    area: Area

    @property
    def ran(self) -> bool:
        return self.arm is not None and self.area.arm is not None

    def speedup(self) -> Speedup:
        s_steps, s_reached = self.area.arm.steps_to(self.area.level)
        m_steps, m_reached = self.arm.steps_to(self.area.level)
        return Speedup.of(s_steps, s_reached == self.area.arm.n, m_steps, m_reached == self.arm.n)

    def difference(self) -> dict:
        """MEDC − sparse learning scores: {"diff", "half"} (Welch 95% CI)."""
        return compare(self.arm.scores(), self.area.arm.scores())

    @property
    def underpowered(self) -> bool:
        return self.difference()["half"] > SWEEP_UNDERPOWERED

    def guided(self) -> tuple[float, float]:
        """(guided share, follow rate), means over the seeds that have them."""
        return _mean(self.arm.guided), _mean(self.arm.follow)

    def difference_text(self) -> str:
        d = self.difference()
        return f"{d['diff']:+.2f} ± {d['half']:.2f}" + (" (under-powered)" if self.underpowered else "")


def _mean(values: Sequence[float]) -> float:
    kept = [v for v in values if not math.isnan(v)]
    return sum(kept) / len(kept) if kept else math.nan


def _percent(x: float, digits: int = 1) -> str:
    return "—" if math.isnan(x) else f"{x:.{digits}%}"


def compare_lower(low: CellResult, high: CellResult) -> str:
    """"supported" when ``low``'s difference is below ``high``'s with disjoint 95% CIs, "not
    supported" when they are disjoint the other way, "not resolved" when the CIs overlap."""
    a, b = low.difference(), high.difference()
    if a["diff"] + a["half"] < b["diff"] - b["half"]:
        return "supported"
    if b["diff"] + b["half"] < a["diff"] - a["half"]:
        return "not supported"
    return "not resolved"


def within(center: CellResult, others: Sequence[CellResult]) -> str:
    """H3's rule: "supported" when every one of ``others``' differences lies within ``center``'s
    95% CI; else "not supported" when one's CI is disjoint from ``center``'s (that setting clearly
    matters), "not resolved" when they overlap."""
    c = center.difference()
    gaps = [(abs(o.difference()["diff"] - c["diff"]), o.difference()["half"]) for o in others]
    if all(gap <= c["half"] for gap, _ in gaps):
        return "supported"
    if any(gap > half + c["half"] for gap, half in gaps):
        return "not supported"
    return "not resolved"


def _blocked(results: Sequence[CellResult]) -> str | None:
    """Why a hypothesis over ``results`` cannot be answered (not run / not testable), or None."""
    missing = sorted({r.cell.setting for r in results if not r.ran})
    if missing:
        return f"not run ({'; '.join(missing)} missing)"
    untestable = sorted({r.area.name for r in results if not r.area.testable})
    if untestable:
        return f"not testable ({', '.join(untestable)}: MDRL-sparse did not pass the learnability gate)"
    return None


def hypotheses(results: dict[tuple[int, float, float], CellResult]) -> list[str]:
    """H1–H3 as SWEEP.md states them, each with its verdict and numbers."""
    grid0, rate0, q0 = SWEEP_PROTOCOL
    small, rate_high = min(SWEEP_GRIDS), max(SWEEP_RATES)
    base = results[(grid0, rate0, q0)]

    def numbers(cells: Sequence[CellResult]) -> str:
        return "; ".join(f"{c.cell.setting}: {c.difference_text()}" for c in cells)

    h1 = [base, results[(small, rate0, q0)]]
    h2 = [results[(grid0, rate_high, q0)], base]
    h3 = [base, *(results[(grid0, rate0, q)] for q in SWEEP_QS if q != q0)]
    lines = []
    for name, claim, cells, judge in (
            ("H1 (rarity)", f"at R_E {rate0:g}, MEDC's advantage grows with the area: the difference at "
             f"{grid0}×{grid0} is lower than at {small}×{small}, with disjoint 95% CIs", h1,
             lambda: compare_lower(h1[0], h1[1])),
            ("H2 (R_E binds)", f"at {grid0}×{grid0}, R_E {rate_high:g} gives a lower difference than R_E "
             f"{rate0:g}, with disjoint CIs", h2, lambda: compare_lower(h2[0], h2[1])),
            ("H3 (Q matters less than R_E)", f"at {grid0}×{grid0}, R_E {rate0:g}, the differences at the "
             f"other Q values both lie within the CI of Q {q0:g}'s", h3, lambda: within(h3[0], h3[1:]))):
        word = _blocked(cells) or judge()
        shown = numbers([c for c in cells if c.ran])
        lines.append(f"- **{name}** — {word}: {claim}. Learning-score differences MEDC − sparse (95% CI): "
                     f"{shown or 'none yet'}.")
    return lines


def area_table(areas: Sequence[Area], min_seeds: int) -> str:
    lines = ["| area | MDRL-sparse seeds | learnability gate | random play finds the source | "
             "sparse's final level L_G | sparse's steps to L_G |", "|---|---|---|---|---|---|"]
    for a in areas:
        if a.arm is None:
            lines.append(f"| {a.name} | 0 | not run | | | |")
            continue
        word = "passed" if a.testable else (f"NOT passed (needs ≥ {min_seeds} seeds and a CI below 0): "
                                            "not testable")
        steps, reached = a.arm.steps_to(a.level)
        lines.append(f"| {a.name} | {a.arm.n} | {word}: {a.gate['diff']:+.2f} ± {a.gate['half']:.2f} | "
                     f"{_percent(a.random_success, 0)} | {a.level:.2f} | {steps:,.0f} ({reached} of "
                     f"{a.arm.n} seeds reach it) |")
    return "\n".join(lines)


def cell_table(results: Sequence[CellResult]) -> str:
    lines = ["| area | R_E | Q | run | seeds | speed-up | MEDC's steps to L_G | learning-score difference "
             "MEDC − sparse ± 95% CI | guided share | expert's move taken |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        c = r.cell
        area = r.area.name + ("" if r.area.testable else " (sparse not run)" if r.area.arm is None
                              else " (not testable)")
        head = f"| {area} | {c.rate:g} | {c.q:g} | `{c.run}` |"
        if not r.ran:
            lines.append(head + " 0 | not run | | | | |")
            continue
        steps, reached = r.arm.steps_to(r.area.level)
        guided, follow = r.guided()
        lines.append(f"{head} {r.arm.n} | {r.speedup().text()} | {steps:,.0f} ({reached} of {r.arm.n}) | "
                     f"{r.difference_text()} | {_percent(guided)} | {_percent(follow, 0)} |")
    return "\n".join(lines)


def heat_map(results: Sequence[CellResult], png) -> None:
    """The speed-up over (area, R_E) at the protocol's Q, and the Q strip at the protocol's area and
    R_E; each cell annotated with the speed-up, the learning-score difference and the guided share
    (blank and grey where not run)."""
    from ..report_plots import RatioMap, plot_ratio_maps

    by_key = {(r.cell.grid, r.cell.rate, r.cell.q): r for r in results}
    grid0, rate0, q0 = SWEEP_PROTOCOL

    def cell(key) -> tuple[float, str]:
        r = by_key.get(key)
        if r is None or not r.ran:
            return math.nan, "not run"
        d = r.difference()
        speed = r.speedup()
        return speed.value, (f"{speed.text()}\n{d['diff']:+.1f} ± {d['half']:.1f}\n"
                             f"{_percent(r.guided()[0])} guided")

    def area(grid: int) -> str:
        untestable = any(r.area.grid == grid and r.area.arm is not None and not r.area.testable
                         for r in results)
        return f"{grid}×{grid}" + ("\n(not testable)" if untestable else "")

    rows = [[cell((g, rate, q0)) for rate in SWEEP_RATES] for g in SWEEP_GRIDS]
    strip = [[cell((grid0, rate0, q)) for q in SWEEP_QS]]
    maps = [RatioMap(f"area × R_E (Q {q0:g})", "R_E", "area", [area(g) for g in SWEEP_GRIDS],
                     [f"{rate:g}" for rate in SWEEP_RATES], [[v for v, _ in row] for row in rows],
                     [[t for _, t in row] for row in rows]),
            RatioMap(f"Q at {grid0}×{grid0}, R_E {rate0:g}", "Q", "", [area(grid0)],
                     [f"{q:g}" for q in SWEEP_QS], [[v for v, _ in strip[0]]], [[t for _, t in strip[0]]])]
    plot_ratio_maps(maps, png, "When do borrowed experts help? MEDC (6 experts) vs MDRL-sparse",
                    "speed-up: sparse's steps to its final level / MEDC's")


def sweep_section(cells: tuple[SweepCell, ...], report, figure) -> str | None:
    """The sweep's section (the sweep's :class:`~medc_lab.figures.SweepMap`): None until a run of the
    sweep's own (not one it borrows from Figs. 6 and 8) has finished on the sweep's seeds."""
    seeds = report.figure_seeds(figure)
    names = dict.fromkeys([n for c in cells for n in (c.sparse, c.run)])
    arms = {name: read_arm(report.seed_rows(name, seeds)) for name in names}
    if not any(arms[n] for n in names if n not in figure.borrowed):
        return None
    areas = {}
    for c in cells:
        if c.grid not in areas:
            gate = report.judge.gate_result(c.sparse, figure.gate_min_seeds, seeds)
            rarity = report.random_success(c.sparse, seeds) if arms[c.sparse] else math.nan
            areas[c.grid] = Area(c.grid, c.sparse, arms[c.sparse], gate, rarity)
    results = [CellResult(c, arms[c.run], areas[c.grid]) for c in cells]
    heat_map(results, report.out / HEATMAP)
    seed_text = f"seeds {min(seeds)}–{max(seeds)}" if seeds else "every seed that ran"
    need = figure.gate_min_seeds or report.scope.gate_min_seeds
    return "\n\n".join([
        "### When do borrowed experts help? (sweep)",
        "The amendment [SWEEP.md](SWEEP.md), fixed before its runs: MEDC with the six users' experts "
        "against MDRL-sparse over the area (at the fixed step limit, reward gets rarer as the area "
        f"grows), R_E and Q, on {seed_text} (Fig. 6's sparse and Fig. 8's MEDC runs give the protocol's "
        "own cell those seeds). It maps effects and adds no verdict to the protocol's.",
        f"![sweep heat map]({HEATMAP})\n\nEach cell of the heat map: the speed-up, the learning-score "
        "difference MEDC − sparse ± 95% CI, and the guided share; grey where not run. Below it, Q at the "
        "protocol's area and R_E.",
        area_table(list(areas.values()), need),
        cell_table(results),
        "**Speed-up**: sparse's training steps to reach L_G (its final level at that area: the mean over "
        "its seeds of its last three evaluations) over MEDC's, each the mean over seeds of the first "
        "evaluation at or below L_G; a seed that never reaches it counts its whole budget, so the "
        "speed-up is then a bound: \"≥\" (a sparse seed never reached it), \"≤\" (a MEDC seed never did), "
        "\"?\" (both: no bound). **Guided share**: the share of training agent-steps taken in "
        "expert-guided episodes (the run's log, weighted by the steps each row covers, then the mean over "
        "seeds); **expert's move taken**: the share of guided agent-steps on which the expert's move was "
        f"taken. A CI half-width above {SWEEP_UNDERPOWERED} steps is under-powered at 3 seeds.",
        "\n".join(hypotheses({(r.cell.grid, r.cell.rate, r.cell.q): r for r in results})),
        "The experts were cloned at the protocol's area; their window observation has the same shape on "
        "every area, so they guide unchanged at the smaller ones, but their quality there is not measured.",
    ])
