"""Markdown tables of ``medc-radbench`` runs: what docs/radbench.md shows, rebuilt from the runs' JSON.

    python -m medc_training.radbench.tables docs/reproduction/radbench/searchers > TABLES.md

Each ``*.json`` of the folder is one run (``medc-radbench``'s last line). Per run: the pooled figures
of every policy with the paired comparison against the run's reference (a verdict from the 95%
interval of the mean length difference: "beats" where its upper bound is below 0, "loses" where
its lower bound is above 0, else "not resolved"), the mean length per obstruction count with the
strongest policy of each count, and the seconds each policy took.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["run_tables", "verdict"]


def verdict(mean: float | None, half: float | None) -> str:
    """The paired verdict of a mean difference (this policy minus the reference, in moves; lower is
    better) with its 95% half-width."""
    if mean is None or half is None:
        return "-"
    if mean + half < 0:
        return "beats"
    if mean - half > 0:
        return "loses"
    return "not resolved"


def _name(policy: str) -> str:
    """A bundle path as its run folder (``.../g20w2-250k/seed0/policy.safetensors`` -> learned
    g20w2-250k/seed0), a controller as itself."""
    if policy.endswith(".safetensors"):
        parts = Path(policy).parts
        return "learned " + "/".join(parts[-3:-1])
    return policy


def _num(x: Any, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def run_tables(doc: dict[str, Any], title: str) -> str:
    """The markdown of one run (``medc-radbench``'s JSON)."""
    policies, ref = doc["policies"], doc["reference"]
    pooled, pairs = doc["pooled"], doc["paired_pooled"]
    sets = len(doc["sets"])
    lines = [f"### {title}", "",
             f"Grid {doc['grid']} × {doc['grid']} m, {doc['agents']} agent(s), {sets} sets × "
             f"{doc['episodes_per_set']} episodes ({sets * doc['episodes_per_set']}), set file "
             f"`{doc['set_file']}` (sha256 `{doc['set_file_sha256'][:16]}…`), count-noise run {doc['run']}; "
             f"reference `{ref}`.", "",
             "| policy | completed | mean length (failures at 120) | median completed [95% CI] | "
             f"paired vs {ref} (moves) | verdict | declared right / declared | seconds |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for p in policies:
        s = pooled["all"][p]
        lo, hi = s["median_ci95"]
        if p == ref:
            pair, word = "-", "reference"
        else:
            c = pairs["all"][p]
            pair = (f"{c['mean_diff']:+.2f} ± {_num(c['mean_diff_ci95'], 2)} "
                    f"(wins {c['wins']}, losses {c['losses']})")
            word = verdict(c["mean_diff"], c["mean_diff_ci95"])
        lines.append(
            f"| {_name(p)} | {100 * s['completion_rate']:.1f}% | {_num(s['mean_length'], 2)} ± "
            f"{_num(s['mean_length_ci95'], 2)} | {_num(s['median_completed_length'], 1)} [{_num(lo, 0)}, "
            f"{_num(hi, 0)}] | {pair} | {word} | {s['declared_correct']} / {s['declared']} | "
            f"{doc['seconds'][p]:.0f} |")
    counts = sorted(int(k[3:]) for k in pooled if k.startswith("obs"))
    lines += ["", "Mean length (failures at 120) by obstruction count; **bold**: the strongest policy of "
              "the row (lowest mean).", "",
              "| obstructions | " + " | ".join(_name(p) for p in policies) + " |",
              "| --- |" + " --- |" * len(policies)]
    for count in counts:
        row = pooled[f"obs{count}"]
        best = min(policies, key=lambda p: row[p]["mean_length"])
        cells = [(f"**{row[p]['mean_length']:.1f}**" if p == best else f"{row[p]['mean_length']:.1f}")
                 for p in policies]
        lines.append(f"| {count} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not Path(args[0]).is_dir():
        print("usage: python -m medc_training.radbench.tables FOLDER (of medc-radbench run JSONs)",
              file=sys.stderr)
        return 2
    for path in sorted(Path(args[0]).glob("*.json")):
        print(run_tables(json.loads(path.read_text()), path.stem))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
