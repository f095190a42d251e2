"""Policies played in different ``medc-radbench`` runs, paired by episode: the episode lines of each
run (``--out``) name the set's hash, the set, the episode and the count-noise run, so a learned team
played later pairs with the searchers played earlier on the same episodes and count noise.

    python -m medc_training.radbench.pairing --reference infotaxis-exact A.episodes.jsonl B.episodes.jsonl

prints, per obstruction group (0-2, 3-4, 5-7) and pooled, each policy's mean length with failures at
the limit and completion, and the paired mean difference against the reference with its 95% t
interval; the last line is JSON. ``--by-snr`` adds each group's SNR bins (the set's: low, medium,
high); ``--parents N`` names a bundle by the N folders above it (default 1: ``medc-s0``), for bundles
whose run folders share a name.
"""

from __future__ import annotations

import argparse
import gzip
import json
import re
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .results import EpisodeResult, paired, summarize
from .scenario import MAX_STEPS

__all__ = ["GROUPS", "episode_record", "group_keys", "load_episodes", "obstructions", "pair_table"]

#: Obstruction-count groups the table reports (the goal is stated on 5-7).
GROUPS: dict[str, tuple[int, ...]] = {"obs0-2": (0, 1, 2), "obs3-4": (3, 4), "obs5-7": (5, 6, 7)}
_FIELDS = ("set_id", "index", "length", "success", "declared_step", "declared_error_m", "track_rmse_m")


def _policy_name(policy: str, parents: int = 1) -> str:
    if policy.endswith(".safetensors"):
        return "/".join(Path(policy).parts[-1 - parents:-1]) or policy
    return policy


def episode_record(policy: str, bench_set: Any, result: EpisodeResult, run: int = 0, **extra: Any
                   ) -> dict[str, Any]:
    """One episode line (``medc-radbench --out``), as :func:`load_episodes` reads it: the policy, the
    set's grid, team and hash (``bench_set``, a :class:`~medc_training.radbench.sets.BenchSet`), the
    count-noise run, ``extra`` (a departure, a temperature, an endgame's tau) and the result's fields."""
    return {"policy": policy, "grid": bench_set.grid, "agents": bench_set.agents, "run": run,
            "set_sha256": bench_set.sha256, **extra, **result.to_json()}


def load_episodes(paths: Iterable[str | Path], parents: int = 1) -> dict[str, dict[tuple, EpisodeResult]]:
    """policy -> {(set_sha256, set_id, index, run): EpisodeResult} from episode-line files, plain or
    gzipped (``.gz``; a bundle named by the ``parents`` folders above it). Raises ValueError for a
    line that is not one, or for one episode of one policy given twice."""
    out: dict[str, dict[tuple, EpisodeResult]] = {}
    for path in paths:
        opener = gzip.open if str(path).endswith(".gz") else open
        with opener(path, "rt", encoding="utf-8") as fh:
            for number, line in enumerate(fh, 1):
                try:
                    doc = json.loads(line)
                    key = (doc["set_sha256"], doc["set_id"], int(doc["index"]), int(doc.get("run", 0)),
                           json.dumps(doc.get("departure", {}), sort_keys=True))
                    result = EpisodeResult(**{k: doc[k] for k in _FIELDS})
                    policy = _policy_name(str(doc["policy"]), parents)
                    if doc.get("temperature"):
                        policy += f"@T{float(doc['temperature']):g}"
                    if doc.get("endgame") is not None:
                        policy += f"+endgame{float(doc['endgame']):g}"
                except (ValueError, KeyError, TypeError) as exc:
                    raise ValueError(f"{path}:{number}: not a medc-radbench episode line ({exc})") from None
                episodes = out.setdefault(policy, {})
                if key in episodes:
                    raise ValueError(f"{path}:{number}: {policy} played episode {key[1:4]} twice")
                episodes[key] = result
    return out


#: A set id: its obstruction count and SNR bin (``obs5-low[:40]``).
_SET_ID = re.compile(r"obs(\d+)-([a-z]+)")


def _set_id_parts(set_id: str) -> tuple[int, str]:
    match = _SET_ID.match(set_id)
    if match is None:
        raise ValueError(f"set id {set_id!r} does not name its obstruction count and SNR bin "
                         "(obsN-BIN, e.g. obs5-low)")
    return int(match.group(1)), match.group(2)


def obstructions(set_id: str) -> int:
    """The obstruction count a set id (``obs5-low[:40]``) names."""
    return _set_id_parts(set_id)[0]


def _snr_name(set_id: str) -> str:
    """The SNR bin a set id (``obs5-low[:40]``) names (the set's, not a value's:
    :func:`medc_training.radbench.scenario.snr_bin` bins a value)."""
    return _set_id_parts(set_id)[1]


def group_keys(keys: list[tuple]) -> dict[str, list[tuple]]:
    """Episode keys (set hash, set id, ...) split into :data:`GROUPS` by the obstruction count their
    set names, and ``all``, each in the given order."""
    groups = {name: [k for k in keys if obstructions(k[1]) in counts] for name, counts in GROUPS.items()}
    groups["all"] = list(keys)
    return groups


def pair_table(episodes: dict[str, dict[tuple, EpisodeResult]], reference: str,
               max_steps: int = MAX_STEPS, by_snr: bool = False) -> dict[str, Any]:
    """Per group and pooled (``by_snr``: and per SNR bin within each): every policy's summary on the
    episodes all policies played, and its paired comparison with ``reference``. Raises ValueError
    when the reference is missing or the policies share no episode."""
    if reference not in episodes:
        raise ValueError(f"reference {reference!r} is not among the policies: {', '.join(episodes)}")
    common = set.intersection(*(set(e) for e in episodes.values()))
    if not common:
        raise ValueError("the policies share no episode (another set file, run or departure?)")
    keys = sorted(common, key=lambda k: (k[1], k[2]))
    groups = group_keys(keys)
    if by_snr:
        for name, chosen in list(groups.items()):
            bins = {k: _snr_name(k[1]) for k in chosen}
            for bin_name in sorted(set(bins.values())):
                groups[f"{name}/{bin_name}"] = [k for k in chosen if bins[k] == bin_name]
    table: dict[str, Any] = {"reference": reference, "episodes": len(keys), "groups": {}}
    for name, chosen in groups.items():
        if not chosen:
            continue
        ref = [episodes[reference][k] for k in chosen]
        rows = {}
        for policy, played in episodes.items():
            mine = [played[k] for k in chosen]
            row = {"summary": summarize(mine, max_steps)}
            if policy != reference:
                row["paired"] = paired(mine, ref, max_steps)
            rows[policy] = row
        table["groups"][name] = rows
    return table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.pairing",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="episode-line files of medc-radbench runs (--out)")
    p.add_argument("--reference", required=True, help="the policy the others are compared with")
    p.add_argument("--by-snr", action="store_true", help="also split every group by the sets' SNR bin")
    p.add_argument("--parents", type=int, default=1,
                   help="name a bundle by this many folders above it (default 1, e.g. medc-s0)")
    args = p.parse_args(argv)
    try:
        if args.parents < 1:
            raise ValueError("--parents must be at least 1")
        table = pair_table(load_episodes(args.files, args.parents), args.reference, by_snr=args.by_snr)
    except (OSError, ValueError) as exc:
        print(f"pairing: {exc}", file=sys.stderr)
        return 2
    for group, rows in table["groups"].items():
        print(f"{group}:")
        for policy, row in rows.items():
            s = row["summary"]
            line = (f"  {policy:<28} mean {s['mean_length']:.2f} ± {s['mean_length_ci95']:.2f}, "
                    f"completed {100 * s['completion_rate']:.1f}% of {s['episodes']}")
            if "paired" in row:
                d = row["paired"]
                line += f"; vs {table['reference']}: {d['mean_diff']:+.2f} ± {d['mean_diff_ci95']:.2f}"
            print(line)
    print(json.dumps(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
