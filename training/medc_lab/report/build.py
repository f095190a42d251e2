"""Building report.md: every figure's panels in order, each figure's closing section, the analysis
after the protocol, then the header above them all."""

from __future__ import annotations

import math
from collections.abc import Collection
from pathlib import Path

from ..catalogue import Scope
from ..figures import Figure, SweepMap, WallTimeRatio
from ..plan import Plan
from .finder import load_curves, report_figures, seed_rows
from .judge import Judge
from .markdown import header, panel_section, wall_time_ratio
from .posthoc import posthoc_section
from .reference_play import random_play
from .references import load_references, regime_name
from .sweep import sweep_section


class Report:
    """The report being built in OUT: its sections in order, the runs it reads (:mod:`.finder`), the
    verdicts of its claims (:attr:`judge`) and the panels with a steps-to-sparse's-level line
    (:attr:`speeds`, for :mod:`.posthoc`)."""

    def __init__(self, out: Path, scale: str, seeds: int, command: str, scope: Scope | None = None,
                 base: dict | None = None) -> None:
        self.out, self.scale, self.seeds, self.command = out, scale, seeds, command
        self.scope = scope or Scope()
        #: The scale's run configuration (grid and step limit name a panel's reference regime).
        self.base = base or {}
        self.judge = Judge(out, self.scope)
        self.sections: list[str] = []
        #: The panels with a steps-to-sparse's-level line: (heading, data, sparse's label).
        self.speeds: list[tuple[str, dict, str]] = []

    def figure_seeds(self, fig: Figure) -> tuple[int, ...] | None:
        """The seeds the report reads for ``fig``: those it plans when it reads only those
        (Figure.planned_seeds_only), else None (all that ran)."""
        if not fig.planned_seeds_only or fig.max_seeds is None:
            return None
        return tuple(range(self.scope.first_seed, self.scope.first_seed + fig.max_seeds))

    def series(self, names: dict[str, str], csv_name: str = "metrics.csv",
               seeds: Collection[int] | None = None) -> dict:
        """{label: (steps, curves, summaries)} of the runs ``names`` (label -> run name) that have
        finished seeds; their learning scores go to the judge."""
        data = {}
        for label, name in names.items():
            steps, curves, summaries = load_curves(self.out, name, csv_name, seeds)
            if curves:
                data[label] = (steps, curves, summaries)
                key = name if csv_name == "metrics.csv" else f"{name}:{csv_name}"
                self.judge.record(key, curves, summaries)
        return data

    def references(self, walls: int, grid: int | None = None) -> dict[str, dict]:
        """The reference lines (:mod:`.references`) of the regime with ``walls`` obstructions on
        the ``grid`` (None: the scale's), or {} when this scope has none or they were not played
        on that regime."""
        if self.scope.reference is None or "grid" not in self.base:
            return {}
        regime = regime_name(grid or self.base["grid"], walls, self.base["max_steps"])
        return load_references(self.out / self.scope.reference / regime)

    def summaries(self, name: str) -> list[dict]:
        """The summary.json of every finished seed of run ``name``."""
        return load_curves(self.out, name)[2]

    def seed_rows(self, name: str, seeds: Collection[int] | None = None) -> list[tuple[dict, list[dict]]]:
        """(summary, metrics.csv rows) of every finished seed of run ``name`` (``seeds``: only those)."""
        return seed_rows(self.out, name, seeds)

    def random_success(self, sparse_run: str, seeds: Collection[int] | None = None) -> float:
        """Random valid moves' success rate on the learnability gate's episodes of ``sparse_run``'s
        seeds (their mean; nan when none ran)."""
        rates = [random_play(self.out, summary["config"], self.scope.gate_random_episodes)["success_rate"]
                 for summary, _ in self.seed_rows(sparse_run, seeds)]
        return sum(rates) / len(rates) if rates else math.nan

    def add(self, text: str) -> None:
        self.sections.append(text)

    def write(self, head: str) -> Path:
        path = self.out / "report.md"
        path.write_text(head + "\n\n".join(self.sections) + "\n")
        return path


def closing_section(r: Report, fig: Figure) -> str | None:
    """The section a figure declares after its panels (:attr:`Figure.extra`), or None."""
    if isinstance(fig.extra, WallTimeRatio):
        ratios = []
        for rs, sparse in fig.extra.pairs:
            s_sparse, s_rs = r.summaries(sparse.name), r.summaries(rs.name)
            if s_sparse and s_rs:
                ratios.append((f"A3W{rs.walls}", (sum(s["train_seconds"] for s in s_rs) / len(s_rs))
                               / (sum(s["train_seconds"] for s in s_sparse) / len(s_sparse))))
        return wall_time_ratio(ratios) if ratios else None
    if isinstance(fig.extra, SweepMap):
        return sweep_section(fig.extra.cells, r, fig)
    return None


def build_report(out: Path, scale: str, seeds: int, command: str, plan: Plan, elapsed: dict) -> Path:
    """Write OUT/report.md (and its figures) from whatever runs exist under OUT/runs/ (``elapsed``:
    seconds per stage run by this invocation, shown in the header); returns its path."""
    r = Report(out, scale, seeds, command, plan.scope, plan.base)
    for fig in report_figures(out / "runs"):
        for panel in fig.panels:
            if not plan.planned(panel.gate):
                continue  # a panel of a team this scope does not train (e.g. an FRL side user's A3W3)
            section = panel_section(r, panel, r.figure_seeds(fig), fig.gate_min_seeds)
            if section:
                r.add(section)
        extra = closing_section(r, fig)
        if extra:
            r.add(extra)
    added = plan.scope.posthoc and posthoc_section(r.judge.claim_records, r.speeds, plan.scope.posthoc,
                                                   plan.scope.planning_sd, not plan.window_eval)
    if added:
        r.add(added)
    return r.write(header(r, plan, elapsed))
