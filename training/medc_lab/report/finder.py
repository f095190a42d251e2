"""Finding what a report reads: the finished seeds of a run, their curves and summaries, the
evaluation config behind a curve, and the figures whose runs exist."""

from __future__ import annotations

import json
from collections.abc import Collection
from pathlib import Path

from ..catalogue import long_tags_on_disk
from ..figures import FIGURES, TAGGED, Figure, tag_markers


def seed_dirs(out: Path, name: str, seeds: Collection[int] | None = None) -> list[Path]:
    """The finished seeds' folders of one run name (``runs/<name>/seed<k>/`` holding its
    summary.json), in order; ``seeds``: only those seeds (None: all)."""
    wanted = None if seeds is None else {f"seed{k}" for k in seeds}
    return [d for d in sorted((out / "runs" / name).glob("seed*"))
            if (d / "summary.json").exists() and (wanted is None or d.name in wanted)]


def load_curves(out: Path, name: str, csv_name: str = "metrics.csv", seeds: Collection[int] | None = None
                ) -> tuple[list[float], list[list[float]], list]:
    """(steps, [episode-length curve per seed], [summary per seed]) of one run name (``seeds``:
    only those seeds)."""
    from medc_training.metrics import read_metrics

    curves, summaries, steps = [], [], []
    for seed_dir in seed_dirs(out, name, seeds):
        if not (seed_dir / csv_name).exists():
            continue
        rows = read_metrics(seed_dir / csv_name)
        if len(rows) > len(steps):
            steps = [r["step"] for r in rows]
        curves.append([r["episode_length"] for r in rows])
        summaries.append(json.loads((seed_dir / "summary.json").read_text()))
    return steps, curves, summaries


def seed_rows(out: Path, name: str, seeds: Collection[int] | None = None) -> list[tuple[dict, list[dict]]]:
    """(summary, metrics.csv rows) of every finished seed of run ``name`` (``seeds``: only those)."""
    from medc_training.metrics import read_metrics

    return [(json.loads((d / "summary.json").read_text()), read_metrics(d / "metrics.csv"))
            for d in seed_dirs(out, name, seeds) if (d / "metrics.csv").exists()]


def eval_config(cfg: dict, csv_name: str = "metrics.csv") -> dict:
    """The config whose evaluation episodes a run's ``csv_name`` measured: the run's own for
    metrics.csv; for an FRL side user's metrics_<AyWz>.csv, the run's with that user's agents, walls
    and environment options (the user is evaluated on its own environment from the run's evaluation
    seed, :mod:`medc_training.frl`). Raises ValueError for a side user the run does not have."""
    if csv_name == "metrics.csv":
        return cfg
    name = csv_name.removeprefix("metrics_").removesuffix(".csv")
    for user in cfg.get("frl_users") or ():
        agents, walls = user.get("agents", cfg["agents"]), user.get("walls", cfg["walls"])
        if f"A{agents}W{walls}" == name:
            return {**cfg, "agents": agents, "walls": walls,
                    "env_options": user.get("env_options", cfg["env_options"])}
    raise ValueError(f"{csv_name}: the run has no FRL user {name!r}")


def report_figures(runs: Path) -> list[Figure]:
    """The figures of the report: every phase's, the tagged supplements once per step count that
    ran; a figure that borrows runs of others (the sweep) once a run of its own has finished."""
    figures = []
    for phase, make in FIGURES.items():
        if phase in TAGGED:
            figures += [make(tag) for tag in long_tags_on_disk(runs, tag_markers(phase))]
            continue
        fig = make()
        own = [run.name for run in fig.runs() if run.name not in fig.borrowed]
        if not fig.borrowed or any(seed_dirs(runs.parent, name) for name in own):
            figures.append(fig)
    return figures
