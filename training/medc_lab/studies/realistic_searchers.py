"""Every searcher against infotaxis on the realistic-search study's fixed episodes, paired by episode.

The realistic-search study (:mod:`medc_lab.studies.realistic_search`) plays each policy on the same
512 seeded episodes per scenario, so two policies' lengths can be compared episode by episode. This
report takes every per-episode file under ``<out>/eval/<scenario>`` (the protocol's policies, the
information-driven searchers and the benchmark-trained team's bundles of ``EXTRA``; probes are
left out) and gives, per scenario and policy, the mean length and success rate with 95% CIs and the
mean paired difference of lengths against ``infotaxis`` (policy minus infotaxis; negative: shorter)
with its 95% t interval. A team of seeds appears per seed and over its seeds: the per-episode mean
of its seeds' lengths paired against infotaxis (the interval holds these bundles' episode noise, not
the seed-to-seed spread, which the 'seed spread' column gives as the lowest and highest seed mean).

``python -m medc_lab.cli.realistic searchers --out docs/reproduction/realistic`` (and ``report``)
writes ``<out>/searchers.md`` and ``<out>/searchers.json``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from medc_training.stats import mean_ci

from .realistic_search import BASELINES, EXTRA, SCENARIOS, SEEDS, TEAM_BUNDLES

#: The policy every other one is paired against.
REFERENCE = "infotaxis"
#: Teams of seeds, reported per seed and over their seeds: name -> its seeds' file names.
TEAMS = {
    "learned": tuple(f"learned-seed{k}" for k in SEEDS),
    "team-post-ft": tuple(TEAM_BUNDLES),
}
#: The single policies, in the report's order (a team's seeds follow its row).
SINGLES = (*BASELINES, *(n for n in EXTRA if n not in TEAM_BUNDLES))


def _load(folder: Path, name: str) -> dict | None:
    path = folder / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _entry(lengths: list[float], successes: list[float], ref: list[float] | None) -> dict:
    entry = {"length": mean_ci(lengths), "success": mean_ci(successes)}
    if ref is not None:
        if len(ref) != len(lengths):
            raise ValueError(f"{len(lengths)} episodes against the reference's {len(ref)}: not paired")
        entry["diff"] = mean_ci([a - b for a, b in zip(lengths, ref)])
    return entry


def _team(data: list[dict], ref: list[float] | None) -> dict:
    """A team over its seeds: per-episode mean of the seeds' lengths and successes, paired."""
    lengths = [sum(vals) / len(vals) for vals in zip(*(d["lengths"] for d in data))]
    successes = [sum(map(float, vals)) / len(vals) for vals in zip(*(d["successes"] for d in data))]
    entry = _entry(lengths, successes, ref)
    means = [sum(d["lengths"]) / len(d["lengths"]) for d in data]
    entry.update(seeds=len(data), seed_spread=(min(means), max(means)))
    return entry


def scenario_rows(folder: Path) -> dict:
    """The paired comparison of one scenario's eval folder: its policies (name -> entry) in the
    report's order, and the shortest single policy with its paired difference to the runner-up."""
    ref_data = _load(folder, REFERENCE)
    ref = [float(v) for v in ref_data["lengths"]] if ref_data else None
    policies: dict[str, dict] = {}
    singles: dict[str, list[float]] = {}

    def add(name: str, data: dict) -> None:
        lengths = [float(v) for v in data["lengths"]]
        singles[name] = lengths
        policies[name] = _entry(lengths, [float(v) for v in data["successes"]], ref)

    for name in SINGLES:
        if (data := _load(folder, name)) is not None:
            add(name, data)
    for team, names in TEAMS.items():
        seeds = [(n, d) for n in names if (d := _load(folder, n)) is not None]
        if len(seeds) > 1:
            policies[f"{team} ({len(seeds)} seeds)"] = _team([d for _, d in seeds], ref)
        for name, data in seeds:
            add(name, data)
    missing = [n for n in EXTRA if n not in singles]
    return {"policies": policies, "not_played": missing, **_shortest(singles)}


def _shortest(singles: dict[str, list[float]]) -> dict:
    """The single policy of lowest mean length, its runner-up and their paired difference."""
    if len(singles) < 2:
        return {}
    ranked = sorted(singles, key=lambda n: sum(singles[n]) / len(singles[n]))
    best, second = ranked[:2]
    diff = mean_ci([a - b for a, b in zip(singles[best], singles[second])])
    return {"shortest": best, "runner_up": second, "shortest_vs_runner_up": diff}


def summarize(out: Path) -> list[dict]:
    """One entry per scenario with an eval folder (see :func:`scenario_rows`)."""
    rows = []
    for sc in SCENARIOS:
        folder = out / "eval" / sc.name
        if folder.is_dir():
            rows.append({"scenario": sc.name, "grid": sc.grid, "walls": sc.walls, **scenario_rows(folder)})
    return rows


def _ci(stat: tuple[float, float], scale: float = 1.0, digits: int = 2, sign: bool = False) -> str:
    mean, half = stat
    if math.isnan(mean):
        return "–"
    return f"{mean * scale:{'+' if sign else ''}.{digits}f} ± {half * scale:.{digits}f}"


def _excludes_zero(stat: tuple[float, float]) -> bool:
    mean, half = stat
    return abs(mean) > half


def _verdict_line(row: dict) -> str:
    """The page's sentence on the scenario's shortest policy."""
    if "shortest" not in row:
        return "Fewer than two policies played."
    best, second = row["shortest"], row["runner_up"]
    vs_ref = row["policies"][best].get("diff")
    head = f"Shortest: **{best}**"
    if best != REFERENCE and vs_ref is not None:
        clear = "excludes 0" if _excludes_zero(vs_ref) else "includes 0"
        head += f", {_ci(vs_ref, sign=True)} steps against {REFERENCE} (interval {clear})"
    d = row["shortest_vs_runner_up"]
    clear = "excludes 0" if _excludes_zero(d) else "includes 0: not told apart"
    return head + f"; against the runner-up {second}: {_ci(d, sign=True)} steps (interval {clear})."


def markdown(rows: list[dict]) -> str:
    """The page: per scenario, one line per policy and the shortest policy's sentence."""
    lines = [f"# Realistic search: every searcher against {REFERENCE}, paired by episode", "",
             "Rebuilt by `python -m medc_lab.cli.realistic searchers` from `eval/<scenario>/*.json` "
             f"(the study's fixed episodes). Δ: mean paired difference of episode lengths, policy minus "
             f"{REFERENCE} (negative: shorter), 95% t interval; ✓: the interval excludes 0. A team over "
             "its seeds pairs the per-episode mean of its seeds; 'seed spread' is its lowest and highest "
             "seed mean.", ""]
    for row in rows:
        lines += [f"## {row['grid']}×{row['grid']}, {row['walls']} walls ({row['scenario']})", "",
                  f"| policy | mean length (steps) | success (%) | Δ vs {REFERENCE} (steps) | excludes 0 |",
                  "| --- | --- | --- | --- | --- |"]
        for name, p in row["policies"].items():
            diff = p.get("diff") if name != REFERENCE else None
            low, high = p.get("seed_spread", (0.0, 0.0))
            spread = f" (seed spread {low:.2f}–{high:.2f})" if "seeds" in p else ""
            lines.append(f"| {name} | {_ci(p['length'])}{spread} | {_ci(p['success'], 100.0, 1)} | "
                         f"{'–' if diff is None else _ci(diff, sign=True)} | "
                         f"{'✓' if diff is not None and _excludes_zero(diff) else ''} |")
        lines += ["", _verdict_line(row)]
        if row["not_played"]:
            lines.append(f"Not played on these episodes: {', '.join(row['not_played'])}.")
        lines.append("")
    return "\n".join(lines)


def report(out: Path) -> dict:
    """Write searchers.md and searchers.json under ``out``; returns each scenario's shortest policy."""
    rows = summarize(out)
    (out / "searchers.md").write_text(markdown(rows))
    (out / "searchers.json").write_text(json.dumps({"reference": REFERENCE, "scenarios": rows}, indent=1))
    return {r["scenario"]: r.get("shortest") for r in rows}
