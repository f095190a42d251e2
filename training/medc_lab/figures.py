"""One declaration per paper figure: the runs it needs and the claims it tests.

Both the job plan (:mod:`.plan`) and the report (:mod:`.report`) are generated from these
declarations, so every run name is written once, in its :class:`Run`. An expert written
``@NAME`` is the catalogue bundle ``models/experts/NAME.safetensors`` (``malicious:@NAME``: that
bundle made malicious); any other spec (``random``, ``biased:A``, ``oracle``) is passed as is.
A run shared by two figures (the sweep's protocol cell is Fig. 8's MEDC run) is the same
:class:`Run`, built by the same helper, so that its job is the same and a finished run is not run
again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from medc_training.envs.names import DEFAULT_APPLICATION

from .catalogue import (
    FAULTY_USERS,
    FRL_USERS,
    OTHER_APPS,
    PROPER5,
    SIX,
    SWEEP_GRIDS,
    SWEEP_PROTOCOL,
    SWEEP_QS,
    SWEEP_RATES,
    SWEEP_SEEDS,
)

GREEDY = "mean episode length (greedy eval)"
SAMPLED = "mean episode length (sampled eval)"


@dataclass(frozen=True)
class SweepCell:
    """One MEDC configuration of the sweep: its area (grid side), R_E and Q, its run and the
    MDRL-sparse run of its area."""

    grid: int
    rate: float
    q: float
    run: str
    sparse: str

    @property
    def setting(self) -> str:
        return f"{self.grid}×{self.grid}, R_E {self.rate:g}, Q {self.q:g}"


@dataclass(frozen=True)
class Run:
    """One configuration, trained once per seed into ``runs/<name>/seed<k>/``. The user of
    interest is a team of ``agents``; other applications than target localization take their
    target options, grid and evaluation from the catalogue (OTHER_APPS)."""

    name: str
    method: str
    env: str = DEFAULT_APPLICATION
    walls: int = 2
    experts: tuple[str, ...] = ()
    frl_users: tuple[dict, ...] = ()
    #: FRL users (by index) whose own evaluation curves are logged too (metrics_<user>.csv).
    side_users: tuple[int, ...] = ()
    #: Evaluate at most this many times per run (None: the scale's interval).
    max_evals: int | None = None
    agents: int = 3
    #: TrainConfig fields set for this run alone, over the scale's ((name, value) pairs: the
    #: sweep's grid, R_E ``expert_rate`` and Q ``q_threshold``).
    options: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class Series:
    """One curve of a figure: a run's evaluations (``csv``: whose, for an FRL side user)."""

    label: str
    run: Run
    csv: str = "metrics.csv"

    @property
    def key(self) -> str:
        return self.run.name if self.csv == "metrics.csv" else f"{self.run.name}:{self.csv}"


@dataclass(frozen=True)
class Claim:
    """The paper's claim "``better`` learns faster than ``worse``"; with a ``margin``, the claim
    that ``better`` is at worst ``margin`` steps of mean episode length behind ``worse``."""

    text: str
    better: Series
    worse: Series
    margin: float | None = None


@dataclass(frozen=True)
class Panel:
    """One plotted figure and its report section: a table of its series, the learnability gate
    of its environment (``gate``, the MDRL-sparse run), its claims, and a closing note. ``grid``:
    the grid side of its runs where it is not the scale's (the sweep's areas), which names the
    regime of its reference lines."""

    heading: str
    png: str
    alt: str
    title: str
    series: tuple[Series, ...]
    gate: Run
    claims: tuple[Claim, ...]
    note: str = ""
    wall: bool = False
    ylabel: str = GREEDY
    grid: int | None = None


@dataclass(frozen=True)
class WallTimeRatio:
    """A section on training wall time: per (RS run, MDRL-sparse run) pair, RS's over sparse's."""

    pairs: tuple[tuple[Run, Run], ...]


@dataclass(frozen=True)
class SweepMap:
    """The sweep's section (:mod:`.report.sweep`): its cells mapped over area, R_E and Q."""

    cells: tuple[SweepCell, ...]


@dataclass(frozen=True)
class Figure:
    """A phase of ``medc-reproduce``: its panels, how many seeds (``seeds``: the plan's "seeds"
    or "other_seeds", at most ``max_seeds``) and which budget (``steps``) its runs get.
    ``extra`` declares a section the report adds after the panels (:class:`WallTimeRatio`,
    :class:`SweepMap`).

    The report's rules for the figure: ``gate_min_seeds``, the seeds its panels' learnability gate
    needs (None: the scope's); ``planned_seeds_only``, whether the report reads only the seeds the
    figure plans (the scope's first ``max_seeds``), also of runs it shares with figures that run
    more seeds; ``borrowed``, the names of its runs that other figures declare: the figure is
    reported only once a run of its own has finished."""

    phase: str
    panels: tuple[Panel, ...]
    steps: str = "steps"
    seeds: str = "seeds"
    max_seeds: int | None = None
    extra: WallTimeRatio | SweepMap | None = field(default=None, compare=False)
    gate_min_seeds: int | None = None
    planned_seeds_only: bool = False
    borrowed: tuple[str, ...] = ()

    def runs(self) -> list[Run]:
        """Every run of the figure, once each (baselines are shared by panels)."""
        seen: dict[str, Run] = {}
        for panel in self.panels:
            for s in panel.series:
                seen.setdefault(s.run.name, s.run)
        return list(seen.values())


def _sparse(w: int) -> Run:
    return Run(f"A3W{w}-sparse", "sparse", walls=w)


def _six(w: int) -> Run:
    """MEDC with the six users' experts (Fig. 8's; the sweep's protocol cell at A3W2)."""
    return Run(f"A3W{w}-medc-six", "medc", walls=w, experts=_bundles(SIX))


def _bundles(names) -> tuple[str, ...]:
    return tuple(f"@{n}" for n in names)


def _faulty(name: str) -> str:
    """A Fig. 9 user as an expert: its own bundle, or the fault FAULTY_USERS gives it."""
    return {"random": "random", "biased": "biased:0", "malicious": f"malicious:@{name}"}.get(
        FAULTY_USERS.get(name, ""), f"@{name}")


def fig6() -> Figure:
    panels = []
    for w in (2, 3):
        sparse = Series("MDRL-sparse", _sparse(w))
        free = Series("MEDC free expert (A1W0)",
                      Run(f"A3W{w}-medc-free", "medc", walls=w, experts=("@A1W0",)))
        complex_ = Series("MEDC complex expert (A1W3)",
                          Run(f"A3W{w}-medc-complex", "medc", walls=w, experts=("@A1W3",)))
        combined = Series("MEDC combined experts",
                          Run(f"A3W{w}-medc-combined", "medc", walls=w, experts=("@A1W0", "@A1W3")))
        panels.append(Panel(
            f"### Fig. 6 — A3W{w}", f"fig6_A3W{w}.png", f"fig6 A3W{w}",
            f"Fig. 6: A3W{w}, MEDC experts vs sparse",
            (sparse, free, complex_, combined), sparse.run, (
                Claim(f"A3W{w}: MEDC free expert beats MDRL-sparse", free, sparse),
                Claim(f"A3W{w}: MEDC complex expert beats MDRL-sparse", complex_, sparse),
                Claim(f"A3W{w}: MEDC combined experts beat MDRL-sparse", combined, sparse),
                Claim(f"A3W{w}: the complex expert (A1W3) helps more than the free expert (A1W0)",
                      complex_, free))))
    return Figure("fig6", tuple(panels))


def fig7(margin: float = 2.0) -> Figure:
    sparse = Series("MDRL-sparse", _sparse(2))
    proper = Series("MEDC 5 proper experts", Run("A3W2-medc-proper5", "medc", experts=_bundles(PROPER5)))
    random = Series("MEDC 5 random experts", Run("A3W2-medc-random5", "medc", experts=("random",) * 5))
    biased = Series("MEDC 5 biased experts",
                    Run("A3W2-medc-biased5", "medc", experts=tuple(f"biased:{a}" for a in (0, 2, 4, 6, 1))))
    malicious = Series("MEDC 5 malicious experts",
                       Run("A3W2-medc-malicious5", "medc", experts=tuple(f"malicious:@{n}" for n in PROPER5)))
    return Figure("fig7", (Panel(
        "### Fig. 7 — resilience to faulty experts (A3W2)", "fig7.png", "fig7",
        "Fig. 7: A3W2, faulty experts",
        (sparse, proper, random, biased, malicious), sparse.run, (
            Claim("proper experts beat MDRL-sparse", proper, sparse),
            Claim("random experts: at worst match MDRL-sparse", random, sparse, margin),
            Claim("biased experts: at worst match MDRL-sparse", biased, sparse, margin),
            Claim("malicious experts: at worst match MDRL-sparse", malicious, sparse, margin)),
        note=f"'At worst match' is judged with a margin of {margin} steps of mean episode length: "
             "held if the faulty run's mean is within the margin, inconclusive if only its CI reaches it."),))


def fig8() -> Figure:
    frl = Run("A3W2-frl8", "frl", frl_users=tuple({"agents": a, "walls": w} for a, w in FRL_USERS),
              side_users=(7,))
    panels, rs_pairs = [], []
    for w in (2, 3):
        sparse = Series("MDRL-sparse", _sparse(w))
        six = Series("MEDC (6 experts)", _six(w))
        rs = Series("RS (BFS shaping)", Run(f"A3W{w}-rs", "rs", walls=w))
        il = Series("IL-assisted RL (6 experts)", Run(f"A3W{w}-il-six", "il", walls=w, experts=_bundles(SIX)))
        # the A3W2 federation's A3W3 user (side user 7) is the A3W3 curve
        fed = Series("FRL (8 users, FedAvg)", frl, "metrics.csv" if w == 2 else "metrics_A3W3.csv")
        rs_pairs.append((rs.run, sparse.run))
        panels.append(Panel(
            f"### Fig. 8 — benchmarks (A3W{w})", f"fig8_A3W{w}.png", f"fig8 A3W{w}",
            f"Fig. 8: A3W{w}, MEDC vs benchmarks", (sparse, six, rs, il, fed), sparse.run, (
                Claim(f"A3W{w}: MEDC beats FRL", six, fed),
                Claim(f"A3W{w}: MEDC beats IL-assisted RL", six, il),
                Claim(f"A3W{w}: MEDC matches or beats RS (paper: slight outperformance)", six, rs)),
            note="FRL wall time is for all 8 users together (they train in one process).", wall=True))

    return Figure("fig8", tuple(panels), extra=WallTimeRatio(tuple(rs_pairs)))


def fig9() -> Figure:
    sparse = Series("MDRL-sparse", _sparse(2))
    faulty = tuple(_faulty(n) for n in SIX)
    users = tuple({"agents": a, "walls": w, **({"fault": FAULTY_USERS[f"A{a}W{w}"]}
                                                 if f"A{a}W{w}" in FAULTY_USERS else {})}
                  for a, w in FRL_USERS)
    medc = Series("MEDC (3 of 6 experts faulty)", Run("A3W2-medc-six-3faulty", "medc", experts=faulty))
    frl = Series("FRL (3 of 8 users faulty)", Run("A3W2-frl8-3faulty", "frl", frl_users=users))
    il = Series("IL (3 of 6 experts faulty)", Run("A3W2-il-six-3faulty", "il", experts=faulty))
    return Figure("fig9", (Panel(
        "### Fig. 9 — 3 faulty users out of 8 (A3W2)", "fig9.png", "fig9",
        "Fig. 9: A3W2, 3 faulty of 8 users",
        (sparse, medc, frl, il), sparse.run, (
            Claim("MEDC beats FRL with faulty users", medc, frl),
            Claim("MEDC beats IL with faulty experts", medc, il)),
        note="Faulty users: A2W1 random, A2W2 biased (always action 0), A3W1 malicious (opposite "
             "of its own model's best move). In FRL they share poisoned parameters (random init / policy "
             "head forced to one action / negated policy head, see medc_training.frl)."),))


def other_expert_sets(spec: dict) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """(run-name suffix, expert specs): the six truthful experts of an application, and the
    same six with the first three replaced by a random, a biased and a malicious one."""
    names = [n for n, _, _ in spec["experts"]]
    truthful = _bundles(names)
    faulty = ("random", "biased:0", f"malicious:@{names[0]}", *truthful[3:])
    return ("", truthful), ("-3faulty", faulty)


def fig10() -> Figure:
    """Figs. 10 (truthful) and 11 (3 faulty experts/users): fleet coordination, maze cleaning."""
    panels = []
    for app, spec in OTHER_APPS.items():
        short, title = spec["short"], spec["title"]
        sparse = Series("MDRL-sparse", Run(f"{short}-sparse", "sparse", env=app, walls=0))
        users = [{"agents": a, "env_options": o} for _, a, o in spec["experts"]]
        users.append({"agents": 3, "env_options": spec["target"]})
        bad = [dict(u) for u in users]
        for u, kind in zip(bad[:3], ("random", "biased", "malicious")):
            u["fault"] = kind
        federations = {"": tuple(users), "-3faulty": tuple(bad)}
        for (suffix, experts), (fig, what) in zip(other_expert_sets(spec), (
                ("10", "truthful experts"), ("11", "3 faulty experts/users"))):
            medc = Series("MEDC (6 experts)",
                          Run(f"{short}-medc{suffix}", "medc", env=app, walls=0, experts=experts))
            frl = Series("FRL (7 users)", Run(f"{short}-frl7{suffix}", "frl", env=app, walls=0,
                                              frl_users=federations[suffix]))
            il = Series("IL (6 experts)", Run(f"{short}-il{suffix}", "il", env=app, walls=0, experts=experts))
            panels.append(Panel(
                f"### Fig. {fig} — {title}, {what}", f"fig{fig}_{short}.png", f"fig{fig} {short}",
                f"Fig. {fig}: {title}, {what}", (sparse, medc, frl, il), sparse.run, (
                    Claim(f"{title} ({what}): MEDC beats FRL", medc, frl),
                    Claim(f"{title} ({what}): MEDC beats IL", medc, il)),
                ylabel=SAMPLED))
    return Figure("fig10", tuple(panels), steps="fleet_maze_steps", seeds="other_seeds")


def long(tag: str) -> Figure:
    """Supplement: A3W2 sparse vs MEDC (6 experts) vs MEDC with the scripted oracle as the one
    expert, for long_steps steps (``tag``, e.g. long1M, prefixes the run names), at most 3 seeds."""
    steps = tag[4:]
    sparse = Series("MDRL-sparse", Run(f"{tag}-A3W2-sparse", "sparse"))
    six = Series("MEDC (6 experts)", Run(f"{tag}-A3W2-medc-six", "medc", experts=_bundles(SIX)))
    oracle = Series("MEDC (scripted oracle expert)",
                    Run(f"{tag}-A3W2-medc-oracle", "medc", experts=("oracle",)))
    return Figure("long", (Panel(
        f"### Supplement — longer runs (A3W2, {steps} steps)", f"{tag}_A3W2.png", tag,
        f"Supplement: A3W2, {steps} steps", (sparse, six, oracle), sparse.run, (
            Claim(f"MEDC (6 trained experts) beats MDRL-sparse over {steps} steps", six, sparse),
            Claim(f"MEDC with a perfect (oracle) expert beats MDRL-sparse over {steps} steps",
                  oracle, sparse)),
        note="The oracle expert sees the target (BFS distance after each move); it is not "
             "something a user could share, and is run only to separate 'MEDC does not help' from "
             "'our experts are too weak to help'."),), steps="long_steps", max_seeds=3)


def long_other(tag: str) -> Figure:
    """Supplement: fleet coordination and maze cleaning, MDRL-sparse vs MEDC vs IL with the six
    experts of Fig. 10, truthful and with 3 faulty (as in Fig. 11), for long_steps steps, at
    most 3 seeds and 20 evaluations per run."""
    steps = tag[4:]
    panels = []
    for app, spec in OTHER_APPS.items():
        short, title = spec["short"], spec["title"]

        def run(name: str, method: str, experts=(), short=short, app=app) -> Run:
            return Run(f"{tag}-{short}-{name}", method, env=app, walls=0, experts=experts, max_evals=20)

        (_, truthful), (_, faulty) = other_expert_sets(spec)
        sparse = Series("MDRL-sparse", run("sparse", "sparse"))
        medc = Series("MEDC (6 experts)", run("medc", "medc", truthful))
        il = Series("IL (6 experts)", run("il", "il", truthful))
        medc3 = Series("MEDC (3 of 6 faulty)", run("medc-3faulty", "medc", faulty))
        il3 = Series("IL (3 of 6 faulty)", run("il-3faulty", "il", faulty))
        panels.append(Panel(
            f"### Supplement — longer runs ({title}, {steps} steps)", f"{tag}_{short}.png", f"{tag} {short}",
            f"Supplement: {title}, {steps} steps", (sparse, medc, il, medc3, il3), sparse.run, (
                Claim(f"{title}: MEDC beats MDRL-sparse over {steps} steps", medc, sparse),
                Claim(f"{title}: MEDC beats IL over {steps} steps", medc, il),
                Claim(f"{title}: MEDC with 3 faulty experts beats MDRL-sparse over {steps} steps",
                      medc3, sparse),
                Claim(f"{title}: MEDC beats IL, both with 3 faulty experts, over {steps} steps", medc3, il3)),
            ylabel=SAMPLED))
    return Figure("long-other", tuple(panels), steps="long_steps", max_seeds=3)


def sweep() -> Figure:
    """The when-do-experts-help sweep (docs/reproduction/claims/SWEEP.md): per area (grid side),
    MDRL-sparse and MEDC with the six users' experts at each R_E (Q 0.05); at the protocol's area
    also each Q (R_E 0.1); 3 seeds. Its panels have no claims (the sweep adds no verdicts to the
    protocol's): its section (:func:`.report.sweep.sweep_section`) maps the effects. The protocol's
    own cell is Fig. 8's MEDC run and its area's sparse Fig. 6's, the same runs (not run again)."""
    grid0, rate0, q0 = SWEEP_PROTOCOL

    def medc(grid: int, rate: float, q: float) -> Run:
        if (grid, rate, q) == SWEEP_PROTOCOL:
            return _six(2)
        setting = f"re{rate:g}" if q == q0 else f"q{q:g}"
        return Run(f"sweep-g{grid}-A3W2-medc-six-{setting}", "medc", experts=_bundles(SIX),
                   options=(("grid", grid), ("expert_rate", rate), ("q_threshold", q)))

    panels, cells = [], []
    for grid in SWEEP_GRIDS:
        sparse = _sparse(2) if grid == grid0 else Run(f"sweep-g{grid}-A3W2-sparse", "sparse",
                                                      options=(("grid", grid),))
        settings = [(rate, q0) for rate in SWEEP_RATES]
        if grid == grid0:
            settings += [(rate0, q) for q in SWEEP_QS if q != q0]
        series = [Series("MDRL-sparse", sparse)]
        for rate, q in settings:
            run = medc(grid, rate, q)
            series.append(Series(f"MEDC R_E {rate:g}" + (f", Q {q:g}" if q != q0 else ""), run))
            cells.append(SweepCell(grid, rate, q, run.name, sparse.name))
        note = ("" if grid == grid0 else f"The experts were cloned at {grid0}×{grid0}; their window "
                f"observation has the same shape here, but their quality on {grid}×{grid} is not measured.")
        panels.append(Panel(
            f"### Sweep — learning curves on {grid}×{grid} (A3W2)", f"sweep_g{grid}.png", f"sweep g{grid}",
            f"Sweep: A3W2, {grid}x{grid}, MEDC (6 experts) by R_E and Q", tuple(series), sparse, (),
            note=note, grid=grid))
    return Figure("sweep", tuple(panels), max_seeds=SWEEP_SEEDS, gate_min_seeds=SWEEP_SEEDS,
                  planned_seeds_only=True, borrowed=(_sparse(2).name, _six(2).name),
                  extra=SweepMap(tuple(cells)))


#: The figures of each phase; the long supplements take the tag of their step count.
FIGURES: dict[str, Callable[..., Figure]] = {
    "fig6": fig6, "fig7": fig7, "fig8": fig8, "fig9": fig9, "fig10": fig10,
    "long": long, "long-other": long_other, "sweep": sweep,
}
#: Phases whose figure is declared per step count (a ``long_tag``).
TAGGED = ("long", "long-other")


def tag_markers(phase: str) -> tuple[str, ...]:
    """What follows ``<tag>-`` in the names of a tagged phase's gate runs, one per panel, to find
    the tags that ran (e.g. ``A3W2-sparse`` for ``long``; ``fleet-sparse`` and ``maze-sparse``
    for ``long-other``, either of which may have run alone)."""
    return tuple(dict.fromkeys(p.gate.name[1:] for p in FIGURES[phase]("").panels))
