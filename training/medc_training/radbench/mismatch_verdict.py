"""The model-mismatch sweep's verdict (docs/learned-team.md, "Model mismatch sweep"), as the protocol
states it.

Every policy played the sweep's worlds on the same episodes and count noise (``scripts/
radbench_mismatch.sh``: ``nominal.episodes.jsonl`` and one ``DEPARTURE.episodes.jsonl`` per
departure, possibly in several folders, e.g. the searchers' and a learned team's). A policy's level in
a world is its mean length with failures counted at the episode limit, over the episodes every policy
played there; its *ratio* is that level over its own nominal one. Where a searcher's ratio is at least
1.25 (it "loses 25%"), each learned policy must complete at least 95% of the episodes and keep its
ratio at most 1.10; the goal is met when that holds for every learned policy at every such departure
(and there is one). Elsewhere the rows are measurements. Beside each learned policy, its paired
difference with a reference searcher (learned - searcher, episode-level Student-t 95% interval).
A folder given as ``LABEL=DIR`` names its policies ``LABEL:NAME``, so two teams whose bundles share
a folder name (``medc-s0``) can be judged side by side.

    python -m medc_training.radbench.mismatch_verdict --searchers infotaxis,infotaxis-exact \\
        --reference infotaxis-exact docs/reproduction/learned-team/mismatch dr=DIR ...

It prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .pairing import load_episodes
from .results import EpisodeResult, paired, summarize
from .scenario import MAX_STEPS

__all__ = ["BOUND", "COMPLETION", "LOSS", "load_sweep", "mismatch_verdict"]

#: A searcher "loses" under a departure when its level is at least this times its nominal one.
LOSS = 1.25
#: Where one does, a learned policy must complete at least this share of the episodes...
COMPLETION = 0.95
#: ...and keep its level within this ratio of its own nominal one.
BOUND = 1.10
NOMINAL = "nominal"

Played = dict[str, dict[tuple, EpisodeResult]]


def load_sweep(folders: Sequence[str | Path]) -> dict[str, Played]:
    """world -> policy -> {episode key: result}, from every ``WORLD.episodes.jsonl`` of ``folders``
    (each ``DIR`` or ``LABEL=DIR``; a policy met twice in one world is refused). Raises ValueError
    when no folder holds the nominal world."""
    worlds: dict[str, list[tuple[str, Path]]] = {}
    for folder in map(str, folders):
        label, sep, path = folder.partition("=")
        label, path = (label, path) if sep else ("", folder)
        if not Path(path).is_dir():
            raise ValueError(f"{path} is not a folder of episode lines")
        for file in sorted(Path(path).glob("*.episodes.jsonl")):
            worlds.setdefault(file.name.removesuffix(".episodes.jsonl"), []).append((label, file))
    if NOMINAL not in worlds:
        raise ValueError(f"no {NOMINAL}.episodes.jsonl in {', '.join(map(str, folders))}")
    out: dict[str, Played] = {}
    for world, files in worlds.items():
        merged: Played = {}
        for label, file in files:
            for name, episodes in load_episodes([file]).items():
                policy = f"{label}:{name}" if label else name
                if policy in merged:
                    raise ValueError(f"{policy} played the {world} world in two files")
                merged[policy] = episodes
        out[world] = merged
    return out


def _common(played: Played) -> list[tuple]:
    common = set.intersection(*(set(e) for e in played.values()))
    if not common:
        raise ValueError("the policies share no episode")
    return sorted(common, key=lambda k: (k[1], k[2], k[3]))


def _level(episodes: dict[tuple, EpisodeResult], keys: list[tuple], max_steps: int) -> dict[str, float]:
    summary = summarize([episodes[k] for k in keys], max_steps)
    return {"mean_length": summary["mean_length"], "completion": summary["completion_rate"]}


def _paired(mine: dict[tuple, EpisodeResult], theirs: dict[tuple, EpisodeResult], keys: list[tuple],
            max_steps: int) -> dict[str, float]:
    comparison = paired([mine[k] for k in keys], [theirs[k] for k in keys], max_steps)
    mean = comparison["mean_diff"]
    half = comparison["mean_diff_ci95"] if comparison["mean_diff_ci95"] is not None else float("nan")
    return {"mean": mean, "lo": mean - half, "hi": mean + half}


def mismatch_verdict(sweep: dict[str, Played], searchers: Sequence[str], reference: str | None = None,
                     max_steps: int = MAX_STEPS, judge: str | None = None) -> dict[str, Any]:
    """The verdict (module docstring) of every policy of ``sweep`` not named in ``searchers``, or
    only of those under the folder label ``judge`` (``LABEL:NAME``; the other learned policies are
    rows to compare with). Raises ValueError when a searcher or learned policy is missing from a
    world, or none is learned (or judged)."""
    learned = sorted({p for played in sweep.values() for p in played} - set(searchers))
    if not learned:
        raise ValueError("no learned policy in the sweep (every policy is a searcher)")
    judged_policies = [p for p in learned if judge is None or p.startswith(f"{judge}:")]
    if not judged_policies:
        raise ValueError(f"no learned policy is labelled {judge!r} (they are {', '.join(learned)})")
    if reference is not None and reference not in searchers:
        raise ValueError(f"the reference {reference!r} is not one of the searchers {list(searchers)}")
    for world, played in sweep.items():
        missing = [p for p in (*searchers, *learned) if p not in played]
        if missing:
            raise ValueError(f"the {world} world was not played by {', '.join(missing)}")
    levels: dict[str, dict[str, dict[str, float]]] = {}
    for world, played in sweep.items():
        keys = _common(played)
        levels[world] = {p: {"episodes": len(keys), **_level(played[p], keys, max_steps)} for p in played}
        if reference is not None:
            for p in learned:
                levels[world][p]["vs_reference"] = _paired(played[p], played[reference], keys, max_steps)
    nominal = levels[NOMINAL]
    worlds: dict[str, Any] = {}
    for world in [NOMINAL, *sorted(w for w in levels if w != NOMINAL)]:
        row = {p: {**v, "ratio": v["mean_length"] / nominal[p]["mean_length"]}
               for p, v in levels[world].items()}
        losing = [s for s in searchers if row[s]["ratio"] >= LOSS] if world != NOMINAL else []
        entry: dict[str, Any] = {"policies": row, "searchers_losing": losing}
        if losing:
            entry["held"] = {p: row[p]["completion"] >= COMPLETION and row[p]["ratio"] <= BOUND
                             for p in judged_policies}
        worlds[world] = entry
    judged = [w for w, e in worlds.items() if e["searchers_losing"]]
    return {"searchers": list(searchers), "learned": learned, "judged_policies": judged_policies,
            "reference": reference,
            "loss": LOSS, "completion": COMPLETION, "bound": BOUND, "worlds": worlds, "judged": judged,
            "goal_met": bool(judged) and all(all(worlds[w]["held"].values()) for w in judged)}


def _print(v: dict[str, Any]) -> None:
    for world, e in v["worlds"].items():
        cells = []
        for p, r in e["policies"].items():
            cell = f"{p} {r['mean_length']:.2f} ({r['ratio']:.2f}x, {100 * r['completion']:.1f}%)"
            if "vs_reference" in r:
                d = r["vs_reference"]
                cell += f" vs {v['reference']} {d['mean']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]"
            cells.append(cell)
        print(f"{world}:\n  " + "\n  ".join(cells))
        if e["searchers_losing"]:
            held = ", ".join(f"{p} {'held' if ok else 'NOT held'}" for p, ok in e["held"].items())
            print(f"  searchers losing >= {v['loss']:g}x: {', '.join(e['searchers_losing'])} -> {held}")
    judged = ", ".join(v["judged"]) or "no departure"
    print(f"judged at: {judged}; goal met: {'yes' if v['goal_met'] else 'no'}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.mismatch_verdict",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("folders", nargs="+", help="folders of the sweep's episode lines (WORLD.episodes.jsonl)")
    p.add_argument("--searchers", required=True, help="the searchers' policy names, comma-separated")
    p.add_argument("--reference", help="a searcher each learned policy is paired with")
    p.add_argument("--judge", metavar="LABEL",
                   help="judge only the learned policies of the folder given as LABEL=DIR (the others "
                        "are shown beside them)")
    args = p.parse_args(argv)
    try:
        searchers = [s for s in args.searchers.split(",") if s]
        verdict = mismatch_verdict(load_sweep(args.folders), searchers, args.reference, judge=args.judge)
    except (OSError, ValueError) as exc:
        print(f"mismatch_verdict: {exc}", file=sys.stderr)
        return 2
    _print(verdict)
    print(json.dumps(verdict))
    return 0


if __name__ == "__main__":
    sys.exit(main())
