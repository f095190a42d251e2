"""The learned-team protocol's verdicts (docs/learned-team.md), computed exactly as it states them.

**On the frozen episodes** (:func:`frozen_verdict`): the learned team of every training seed and the
yardstick played the same episodes with the same count noise (``medc-radbench --out`` episode lines,
paired by set hash, set, episode and run). Lengths count a failure at the episode limit. Per seed:
the mean length on the 5-7 obstruction sets against 0.85 x the yardstick's, and the episode-level
paired interval of (learned - 0.85 x yardstick). The seeds pooled: per episode, the learned lengths
(and completions) averaged over the seeds, paired with the yardstick on that episode, a Student-t
95% interval over the episodes: of (learned - 0.85 x yardstick) on 5-7 obstructions, of the
completion difference there, and of (learned - yardstick) on every obstruction count. Over seeds
(secondary): the seeds' mean differences, a t interval with seeds - 1 degrees of freedom.

- *Goal met*: on 5-7 obstructions every seed's mean is at most 0.85 x the yardstick's, the pooled
  upper bound of (learned - 0.85 x yardstick) is below 0 and the completion difference's lower
  bound is at least -1 point; and on every other obstruction count the upper bound of (learned -
  yardstick) is at most 5% of the yardstick's mean there (non-inferiority).
- Per obstruction count: *beats* (upper bound below 0), *matches* (not beats; upper bound within
  the 5% margin), *loses* (lower bound above 0: shown longer), *not resolved* (otherwise: the
  interval reaches past the margin and below 0). Only *beats* and *matches* are non-inferior.

**A gate on the validation episodes** (:func:`seeds_gate`): a candidate bundle of every training seed
against another bundle of the same seed (the team it would replace), both having played the same
validation episodes. Per seed the paired difference (candidate - other), and the seeds pooled as
above: per episode the seeds' differences averaged, a Student-t 95% interval over the episodes, per
obstruction group (0-2, 3-4, 5-7) and over all. The gate *passes* when the pooled upper bound is below
0 both on 5-7 obstructions and over all.

**Steps to the yardstick** (:func:`steps_to_level`, the protocol's MEDC claim): every run's piece
bundles played the validation episodes (``validation-STEPS.episodes.jsonl`` in its folder); a run
reaches the yardstick's level at the first piece whose mean length is at most the yardstick's on the
same episodes, and a run that never does counts at its budget (censored). MEDC's claim against
another method is *supported* when MEDC is first on every seed and the paired t interval of
log(steps_other / steps_medc) over the seeds excludes 0; otherwise *not resolved*.

    python -m medc_training.radbench.verdict frozen --yardstick SEARCHERS.episodes.jsonl \\
        --reference infotaxis-exact RUN/frozen-g20-a3.episodes.jsonl ...
    python -m medc_training.radbench.verdict steps --yardstick VALIDATION_SEARCHERS.episodes.jsonl \\
        --reference infotaxis-exact --budget 2000000 medc=RUN,RUN,RUN sparse=RUN,RUN,RUN ...
    python -m medc_training.radbench.verdict gate --candidate NEW_S0.episodes.jsonl NEW_S1... \\
        --against OLD_S0.episodes.jsonl OLD_S1...

Each prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from medc_training.stats import mean_ci

from .pairing import group_keys, load_episodes, obstructions
from .results import scored_length
from .scenario import MAX_STEPS, OBSTRUCTION_COUNTS

__all__ = ["GOAL_COUNTS", "GOAL_RATIO", "MARGIN", "frozen_verdict", "seeds_gate", "steps_to_level"]

#: The obstruction counts the goal is stated on, and the ratio of the yardstick it asks for.
GOAL_COUNTS: tuple[int, ...] = (5, 6, 7)
GOAL_RATIO = 0.85
#: The non-inferiority margin, a fraction of the yardstick's mean length.
MARGIN = 0.05
#: The completion difference's lower bound the goal allows (one point).
COMPLETION_SLACK = 0.01


def _interval(values: Sequence[float]) -> dict[str, float]:
    mean, half = mean_ci(list(values))
    return {"n": len(values), "mean": mean, "lo": mean - half, "hi": mean + half}


def _only_policy(path: str | Path) -> dict:
    played = load_episodes([path])
    if len(played) != 1:
        raise ValueError(f"{path}: one learned team per file is needed, found {sorted(played)}")
    return next(iter(played.values()))


def frozen_verdict(yardstick: dict, seeds: Sequence[dict], max_steps: int = MAX_STEPS) -> dict[str, Any]:
    """The verdict (module docstring) of the learned team's ``seeds`` (each {episode key:
    EpisodeResult}, one per training seed) against ``yardstick`` on the episodes all of them
    played. Raises ValueError when there are no seeds or no shared episode."""
    if not seeds:
        raise ValueError("no learned team to judge")
    common = set(yardstick).intersection(*(set(s) for s in seeds))
    if not common:
        raise ValueError("the learned teams and the yardstick share no episode")
    keys = sorted(common, key=lambda k: (k[1], k[2]))
    count_of = {k: obstructions(k[1]) for k in keys}

    def lengths(played: dict, chosen: list) -> list[float]:
        return [scored_length(played[k], max_steps) for k in chosen]

    def seed_mean(chosen: list) -> list[float]:  # per episode, the learned length averaged over seeds
        return [sum(scored_length(s[k], max_steps) for s in seeds) / len(seeds) for k in chosen]

    goal = [k for k in keys if count_of[k] in GOAL_COUNTS]
    out: dict[str, Any] = {"episodes": len(keys), "seeds": len(seeds), "goal_counts": list(GOAL_COUNTS),
                           "goal_ratio": GOAL_RATIO, "margin": MARGIN}
    checks: dict[str, bool] = {}
    if goal:
        y = lengths(yardstick, goal)
        y_mean = sum(y) / len(y)
        per_seed = []
        for s in seeds:
            mine = lengths(s, goal)
            m = sum(mine) / len(mine)
            per_seed.append({"mean": m, "ratio": m / y_mean if y_mean else math.inf,
                             "vs_goal": _interval([a - GOAL_RATIO * b for a, b in zip(mine, y)])})
        pooled = _interval([a - GOAL_RATIO * b for a, b in zip(seed_mean(goal), y)])
        done = [sum(float(s[k].success) for s in seeds) / len(seeds) - float(yardstick[k].success)
                for k in goal]
        completion = _interval(done)
        out["goal"] = {"episodes": len(goal), "yardstick_mean": y_mean, "per_seed": per_seed,
                       "pooled_vs_goal": pooled, "completion_diff": completion,
                       "over_seeds_vs_goal": _interval([p["vs_goal"]["mean"] for p in per_seed])}
        checks["every_seed_at_most_ratio"] = all(p["ratio"] <= GOAL_RATIO for p in per_seed)
        checks["pooled_below_ratio"] = pooled["hi"] < 0
        checks["completion_no_lower"] = completion["lo"] >= -COMPLETION_SLACK
    counts: dict[str, Any] = {}
    for c in OBSTRUCTION_COUNTS:
        chosen = [k for k in keys if count_of[k] == c]
        if not chosen:
            continue
        y = lengths(yardstick, chosen)
        y_mean = sum(y) / len(y)
        learned = seed_mean(chosen)
        diff = _interval([a - b for a, b in zip(learned, y)])
        seed_diffs = [sum(a - b for a, b in zip(lengths(s, chosen), y)) / len(y) for s in seeds]
        verdict = ("beats" if diff["hi"] < 0 else "matches" if diff["hi"] <= MARGIN * y_mean
                   else "loses" if diff["lo"] > 0 else "not resolved")
        counts[str(c)] = {"episodes": len(chosen), "yardstick_mean": y_mean,
                          "learned_mean": sum(learned) / len(learned), "pooled_diff": diff,
                          "over_seeds_diff": _interval(seed_diffs), "verdict": verdict}
        if c not in GOAL_COUNTS:
            checks[f"non_inferior_at_{c}"] = verdict in ("beats", "matches")
    out["counts"] = counts
    out["checks"] = checks
    out["goal_met"] = bool(goal) and all(checks.values())
    return out


def seeds_gate(pairs: Sequence[tuple[dict, dict]], max_steps: int = MAX_STEPS) -> dict[str, Any]:
    """The validation gate (module docstring): ``pairs`` holds, per training seed, (candidate, other),
    each {episode key: EpisodeResult}; compared on the episodes every one of them played. Raises
    ValueError when there is no pair or no shared episode."""
    if not pairs:
        raise ValueError("no seed to compare")
    played = [d for pair in pairs for d in pair]
    common = set(played[0]).intersection(*(set(d) for d in played[1:]))
    if not common:
        raise ValueError("the bundles share no validation episode (another set file?)")
    keys = sorted(common, key=lambda k: (k[1], k[2]))
    out: dict[str, Any] = {"episodes": len(keys), "seeds": len(pairs), "groups": {}}
    for name, chosen in group_keys(keys).items():
        if not chosen:
            continue
        lengths = [([scored_length(new[k], max_steps) for k in chosen],
                    [scored_length(old[k], max_steps) for k in chosen]) for new, old in pairs]
        diffs = [[a - b for a, b in zip(mine, theirs)] for mine, theirs in lengths]
        candidate = [sum(mine) / len(mine) for mine, _ in lengths]
        out["groups"][name] = {
            "episodes": len(chosen), "candidate_means": candidate,
            "per_seed": [_interval(d) for d in diffs],
            "pooled": _interval([sum(column) / len(pairs) for column in zip(*diffs)])}
    needed = [g for g in ("obs5-7", "all") if g in out["groups"]]
    out["passes"] = len(needed) == 2 and all(out["groups"][g]["pooled"]["hi"] < 0 for g in needed)
    return out


def _validation_curve(run: Path, reference: dict, max_steps: int) -> list[tuple[int, float, float]]:
    """(steps, the run's mean length, the yardstick's on the same episodes) for every piece bundle
    of ``run`` that has played the validation episodes to the end (its ``validation-STEPS.json``
    written), by steps."""
    curve = []
    for path in run.glob("validation-*.episodes.jsonl"):
        match = re.fullmatch(r"validation-(\d+)\.episodes\.jsonl", path.name)
        if match is None or not (run / f"validation-{match.group(1)}.json").exists():
            continue  # not a piece's play, or one still being played (its summary comes last)
        played = _only_policy(path)
        keys = sorted(set(played) & set(reference), key=lambda k: (k[1], k[2]))
        if not keys:
            raise ValueError(f"{path}: no episode shared with the yardstick (another validation file?)")
        mine = sum(scored_length(played[k], max_steps) for k in keys) / len(keys)
        ref = sum(scored_length(reference[k], max_steps) for k in keys) / len(keys)
        curve.append((int(match.group(1)), mine, ref))
    return sorted(curve)


def _seed_of(run: Path) -> int:
    try:
        return int(json.loads((run / "summary.json").read_text(encoding="utf-8"))["config"]["seed"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{run}: no run summary naming its seed ({exc})") from None


def steps_to_level(reference: dict, runs: dict[str, Sequence[str | Path]], budget: int,
                   focus: str = "medc", max_steps: int = MAX_STEPS) -> dict[str, Any]:
    """The steps every run needs to reach the yardstick's level on the validation episodes and the
    claim of ``focus`` against every other method (module docstring). ``runs``: method -> run
    folders, paired by the training seed their summaries name. Raises ValueError when ``focus`` is
    missing or a method lacks a seed that ``focus`` has."""
    if focus not in runs:
        raise ValueError(f"the claim needs runs of {focus!r}; given {sorted(runs)}")
    table: dict[str, dict[int, dict[str, Any]]] = {}
    for method, folders in runs.items():
        table[method] = {}
        for folder in folders:
            run = Path(folder)
            curve = _validation_curve(run, reference, max_steps)
            reached = next((s for s, mine, ref in curve if mine <= ref), None)
            table[method][_seed_of(run)] = {
                "run": str(run),
                "curve": [{"steps": s, "mean_length": m, "yardstick": r} for s, m, r in curve],
                "reached": reached, "steps": reached if reached is not None else budget,
                "censored": reached is None}
    claims: dict[str, Any] = {}
    seeds = sorted(table[focus])
    for method in runs:
        if method == focus:
            continue
        missing = [s for s in seeds if s not in table[method]]
        if missing:
            raise ValueError(f"{method} has no run for seed(s) {missing} that {focus} has")
        ratios = [math.log(table[method][s]["steps"] / table[focus][s]["steps"]) for s in seeds]
        first = all(table[focus][s]["steps"] < table[method][s]["steps"] for s in seeds)
        interval = _interval(ratios)
        claims[method] = {"seeds": seeds, "log_ratio": interval, "first_on_every_seed": first,
                          "verdict": "supported" if first and interval["lo"] > 0 else "not resolved"}
    return {"focus": focus, "budget": budget, "runs": table, "claims": claims}


def _fmt(i: dict[str, float]) -> str:
    return f"{i['mean']:+.2f} [{i['lo']:+.2f}, {i['hi']:+.2f}]"


def _print_frozen(v: dict[str, Any]) -> None:
    print(f"{v['episodes']} episodes, {v['seeds']} seeds")
    if "goal" in v:
        g = v["goal"]
        print(f"obstructions {'-'.join(map(str, (v['goal_counts'][0], v['goal_counts'][-1])))} "
              f"({g['episodes']} episodes): yardstick {g['yardstick_mean']:.2f}")
        for k, p in enumerate(g["per_seed"]):
            print(f"  seed #{k}: {p['mean']:.2f} ({p['ratio']:.3f} x); learned - {v['goal_ratio']} x "
                  f"yardstick {_fmt(p['vs_goal'])}")
        print(f"  seeds pooled: learned - {v['goal_ratio']} x yardstick {_fmt(g['pooled_vs_goal'])}; "
              f"completion difference {_fmt(g['completion_diff'])}")
    for c, row in v["counts"].items():
        print(f"  {c} obstructions: learned {row['learned_mean']:.2f}, "
              f"yardstick {row['yardstick_mean']:.2f}, "
              f"difference {_fmt(row['pooled_diff'])} -> {row['verdict']}")
    print("checks: " + ", ".join(f"{k} {'yes' if ok else 'NO'}" for k, ok in v["checks"].items()))
    print(f"goal met: {'yes' if v['goal_met'] else 'no'}")


def _print_gate(v: dict[str, Any]) -> None:
    print(f"{v['episodes']} paired episodes, {v['seeds']} seeds; candidate - other:")
    for name, g in v["groups"].items():
        seeds = ", ".join(f"#{k} {m:.2f} {_fmt(i)}" for k, (m, i) in
                          enumerate(zip(g["candidate_means"], g["per_seed"])))
        print(f"  {name} ({g['episodes']}): pooled {_fmt(g['pooled'])}; per seed {seeds}")
    verdict = "passes" if v["passes"] else "does not pass"
    print(f"gate (pooled upper bound below 0 on obs5-7 and all): {verdict}")


def _print_steps(v: dict[str, Any]) -> None:
    for method, seeds in v["runs"].items():
        for seed, row in sorted(seeds.items()):
            points = ", ".join(f"{p['steps'] // 1000}k {p['mean_length']:.1f}/{p['yardstick']:.1f}"
                               for p in row["curve"])
            reached = f"{row['reached']:,}" if row["reached"] is not None else f"not by {v['budget']:,}"
            print(f"{method} seed {seed}: level reached at {reached} ({points})")
    for method, c in v["claims"].items():
        print(f"{v['focus']} vs {method}: log(steps_{method} / steps_{v['focus']}) {_fmt(c['log_ratio'])}, "
              f"first on every seed: {'yes' if c['first_on_every_seed'] else 'no'} -> {c['verdict']}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.verdict",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    f = sub.add_parser("frozen", help="the learned team against the yardstick on the frozen episodes")
    f.add_argument("seeds", nargs="+", help="one episode-line file per training seed (medc-radbench --out)")
    s = sub.add_parser("steps", help="steps to the yardstick's level on the validation episodes")
    s.add_argument("runs", nargs="+", help="METHOD=RUN_FOLDER,RUN_FOLDER,...")
    s.add_argument("--budget", type=int, required=True, help="the runs' training budget (censoring)")
    s.add_argument("--focus", default="medc", help="the method whose claim is judged (default medc)")
    g = sub.add_parser("gate", help="candidate bundles against other bundles of the same seeds, "
                                    "on the episodes both played (the validation episodes for a gate)")
    g.add_argument("--candidate", nargs="+", required=True,
                   help="one episode-line file per training seed: the candidate bundles' play")
    g.add_argument("--against", nargs="+", required=True,
                   help="one episode-line file per training seed, in the same order: the bundles it "
                        "would replace")
    for q in (f, s):
        q.add_argument("--yardstick", required=True, help="episode lines holding the yardstick's episodes")
        q.add_argument("--reference", required=True, help="the yardstick's policy name in that file")
    args = p.parse_args(argv)
    try:
        verdict = _gate(args) if args.what == "gate" else _against_yardstick(args)
    except (OSError, ValueError) as exc:
        print(f"verdict: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(verdict))
    return 0


def _gate(args: argparse.Namespace) -> dict[str, Any]:
    if len(args.candidate) != len(args.against):
        raise ValueError(f"--candidate names {len(args.candidate)} files and --against "
                         f"{len(args.against)}: give one of each per training seed")
    verdict = seeds_gate([(_only_policy(a), _only_policy(b)) for a, b in zip(args.candidate, args.against)])
    _print_gate(verdict)
    return verdict


def _against_yardstick(args: argparse.Namespace) -> dict[str, Any]:
    played = load_episodes([args.yardstick])
    if args.reference not in played:
        raise ValueError(f"{args.yardstick} holds no {args.reference!r} (it holds {sorted(played)})")
    reference = played[args.reference]
    if args.what == "frozen":
        verdict = frozen_verdict(reference, [_only_policy(path) for path in args.seeds])
        _print_frozen(verdict)
        return verdict
    runs: dict[str, list[str]] = {}
    for item in args.runs:
        method, sep, folders = item.partition("=")
        if not sep or not method or not folders:
            raise ValueError(f"{item!r}: give METHOD=RUN_FOLDER,RUN_FOLDER,...")
        runs.setdefault(method, []).extend(x for x in folders.split(",") if x)
    verdict = steps_to_level(reference, runs, args.budget, focus=args.focus)
    _print_steps(verdict)
    return verdict


if __name__ == "__main__":
    sys.exit(main())
