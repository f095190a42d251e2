"""`medc-radbench`: play the radiation-search field's benchmark (RAD-A2C's test sets on a grid) and
report what the field reports, per set and pooled, with the sets' SHA-256.

    medc-radbench --quick                                  # a stated subset, about a minute on 2 cores
    medc-radbench greedy infotaxis --grid 20 --agents 1    # every set of a frozen file, 200 episodes each
    medc-radbench infotaxis models/my-team.safetensors --agents 3 --obstructions 0,7 --snr low
    medc-radbench --cost infotaxis space-aware --agents 3 --batch 256   # what one decision costs
    medc-radbench --list                                   # the frozen files and sets, hashes checked
    medc-radbench --generate /tmp/sets                     # write the set files again from their seed

POLICY is ``random``, a classical controller (gradient, greedy, infotaxis, or an information-driven
searcher: infotaxis-exact, space-aware, infotaxis-2step, team-infotaxis, team-space-aware) or a bundle trained
under the realistic sensing preset; bundle paths joined by ``+`` play as one ensemble (each move
from the members' mean probabilities, ``medc_training.bundle.ensemble``). Every policy plays the
same episodes with the same count noise; the first policy (``--reference``) is compared with each
other one episode by episode (paired).

``--quick`` plays grid 20, 1 agent, obstruction counts 0, 3 and 7, every SNR bin, the first 8
episodes of each set (2 per SNR sub-bin: 72 episodes per policy), with random, gradient, greedy and
infotaxis: under two minutes on the 2-core development machine.

Human-readable lines go to stdout (none with --quiet); the last line is one JSON object: per set its
SHA-256 and every policy's figures (medc_training.radbench.results), pooled by obstruction count, by
SNR bin and overall, the paired comparisons, the set file's SHA-256 and the time each policy took.
docs/radbench.md states the scenario and every difference from RAD-A2C.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: What can run a bundle's network in ``--cost``'s node decision: medc_training.bundle.runtime.RUNTIMES
#: (named here, so that building the command line imports no torch).
RUNTIMES = ("auto", "onnxruntime", "torch")
QUICK = {"grid": 20, "agents": 1, "obstructions": (0, 3, 7), "snrs": ("low", "medium", "high"), "episodes": 8,
         "policies": ("random", "gradient", "greedy", "infotaxis")}


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or any(not 0 <= v <= 7 for v in values):
        raise argparse.ArgumentTypeError(f"obstruction counts are integers in 0..7, got {text!r}")
    return values


def _snr_list(text: str) -> list[str]:
    from ..radbench.scenario import SNR_BINS

    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in SNR_BINS]
    if not values or bad:
        raise argparse.ArgumentTypeError(f"SNR bins are {', '.join(SNR_BINS)}, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    from ..console import QUIET_HELP, HelpFormatter, epilog

    p = argparse.ArgumentParser(prog="medc-radbench", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter, epilog=epilog(__doc__))
    p.add_argument("policies", nargs="*", metavar="POLICY",
                   help="random, a controller's name, a bundle path or bundle paths joined by '+' (an "
                        "ensemble) (default: random gradient greedy infotaxis)")
    p.add_argument("--quick", action="store_true", help="the stated subset above (overrides the set options)")
    p.add_argument("--grid", type=int, choices=(20, 30), help="the area: 20 or 30 cells of 1 m (default 20)")
    p.add_argument("--agents", type=int, choices=(1, 3), help="team size (default 1, RAD-A2C's)")
    p.add_argument("--obstructions", type=_int_list, help="obstruction counts, e.g. 0,3,7 (default all, 0-7)")
    p.add_argument("--snr", type=_snr_list, help="SNR bins, e.g. low,high (default all three)")
    p.add_argument("--episodes", type=int,
                   help="the first N episodes of each set (default all 200; a multiple of 4 keeps the SNR "
                        "sub-bins balanced)")
    p.add_argument("--first", type=int, default=0,
                   help="start at this episode of each set (default 0: --episodes N plays episodes 0..N-1; "
                        "episode lines keep each episode's index in its set)")
    p.add_argument("--reference", help="the policy the others are compared with (default the first)")
    p.add_argument("--sets-file", type=Path, help="a set file of your own instead of the frozen one")
    p.add_argument("--sha256", help="with --sets-file: the SHA-256 the file must have")
    p.add_argument("--run", type=int, default=0,
                   help="Monte Carlo run of the count noise (0: each episode's own stream; another run "
                        "draws other counts for the same episodes)")
    p.add_argument("--departure", metavar="KEY=NUMBER,...",
                   help="the world departs from the team's and the searchers' model, e.g. transmission=0.3 "
                        "(obstructions let 30%% through), efficiency=0.7, strength_scale=2, background=80, "
                        "position_noise=0.2 (medc_training.radbench.departure; default: the nominal world)")
    p.add_argument("--prior-background", metavar="LOW,HIGH,LEVELS",
                   help="the team's estimator weighs backgrounds uniform over LOW-HIGH counts/s at LEVELS "
                        "levels instead of the model's 10-50 at 8, for every policy of the run (a bundle "
                        "trained under a prior plays under its own, and is refused under another)")
    p.add_argument("--endgame", type=float, metavar="TAU",
                   help="every bundle plays with the classical endgame: once the team's posterior holds TAU "
                        "of its mass on one cell, each agent that can reach that cell's success region "
                        "walks a shortest path there (medc_training.radbench.endgame; with --cost, in the "
                        "agent node's decision too); 1: never; controllers are unaffected")
    p.add_argument("--temperature", type=float, default=0.0,
                   help="a bundle samples its move from softmax(logits / T) instead of taking the most "
                        "probable one (0, the default: the most probable; controllers are unaffected)")
    p.add_argument("--batch", type=int, default=100, help="episodes played at once")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--out", type=Path, help="write every played episode here (JSON lines)")
    p.add_argument("--overwrite", action="store_true", help="replace what is already at --out")
    p.add_argument("--cost", action="store_true",
                   help="measure what one decision costs instead of playing the sets: each policy on the "
                        "first episodes of obs3-medium of the --grid/--agents file, at B = 1 and "
                        "B = --batch, and as an agent node decides (medc_training.radbench.cost)")
    p.add_argument("--runtime", choices=RUNTIMES, default="auto",
                   help="with --cost: what runs a bundle's network in the agent node's decision (auto, the "
                        "agent nodes' default: onnxruntime where it agrees with PyTorch; "
                        "medc_training.bundle.runtime)")
    p.add_argument("--list", action="store_true",
                   help="list the frozen set files and sets with their SHA-256")
    p.add_argument("--generate", type=Path, metavar="DIR",
                   help="write the set files (every grid and team size, or those of --grid/--agents) "
                        "into DIR")
    p.add_argument("--seed", type=int,
                   help="with --generate: the generator's seed (default the frozen sets')")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    return p


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def _fmt(summary: dict[str, Any]) -> str:
    def num(x, digits=1):
        return "-" if x is None else f"{x:.{digits}f}"

    lo, hi = summary["median_ci95"]
    rate = 100 * (summary["completion_rate"] or 0)
    return (f"completed {summary['completed']}/{summary['episodes']} ({rate:.0f}%), "
            f"median {num(summary['median_completed_length'], 0)} [{num(lo, 0)}, {num(hi, 0)}], "
            f"mean {num(summary['mean_length'])} ± {num(summary['mean_length_ci95'])}, "
            f"declared {summary['declared']} (error {num(summary['declared_error_m_mean'], 2)} m, "
            f"step {num(summary['declared_step_mean'])})")


def _list(args: argparse.Namespace) -> int:
    from ..radbench.sets import FROZEN, SETS_DIR, load_file

    files = {}
    for name in sorted(FROZEN):
        sets, digest = load_file(SETS_DIR / name)
        _say(args, f"{name}  sha256 {digest}  (checked)")
        for s in sets:
            _say(args, f"  {s.id:<14} {len(s.episodes)} episodes  sha256 {s.sha256}")
        files[name] = {"sha256": digest, "grid": sets[0].grid, "agents": sets[0].agents,
                       "sets": {s.id: s.sha256 for s in sets}}
    print(json.dumps({"benchmark": "medc-radbench", "files": files}))
    return 0


def _generate(args: argparse.Namespace) -> int:
    from ..console import progress_bar
    from ..radbench.scenario import DEFAULT_SEED, GRIDS, OBSTRUCTION_COUNTS, SNR_BINS
    from ..radbench.sets import FROZEN, FROZEN_EPISODES, file_name, generate_file, write_file

    grids = [args.grid] if args.grid else sorted(GRIDS)
    teams = [args.agents] if args.agents else [1, 3]
    seed = DEFAULT_SEED if args.seed is None else args.seed
    episodes = args.episodes or FROZEN_EPISODES
    args.generate.mkdir(parents=True, exist_ok=True)
    out = {}
    total = len(grids) * len(teams) * len(OBSTRUCTION_COUNTS) * len(SNR_BINS)
    with progress_bar(total, unit="set", disable=args.quiet) as bar:
        for grid in grids:
            for agents in teams:
                start = time.perf_counter()
                doc = generate_file(grid, agents, episodes, seed, progress=lambda: bar.update(1))
                name = file_name(grid, agents)
                digest = write_file(doc, args.generate / name)
                same = digest == FROZEN.get(name)
                rates = {s["id"]: s["stats"]["rejection_rate"] for s in doc["sets"]}
                out[name] = {"sha256": digest, "matches_frozen": same,
                             "seconds": round(time.perf_counter() - start, 2), "rejection_rate": rates}
                if not args.quiet:
                    bar.write(f"{args.generate / name}: sha256 {digest} "
                              f"({'the frozen file' if same else 'differs from the frozen file'})")
    print(json.dumps({"benchmark": "medc-radbench", "generated": out, "seed": seed, "episodes": episodes}))
    return 0


def _pool(results: dict[str, dict[str, list]], keys: Sequence[str]) -> dict[str, list]:
    """policy -> the results of the sets ``keys``, concatenated in set order."""
    policies = next(iter(results.values())).keys()
    return {p: [r for k in keys for r in results[k][p]] for p in policies}


def _report(args: argparse.Namespace, sets: list, results: dict[str, dict[str, list]], policies: list[str],
            reference: str) -> tuple[dict, dict, dict]:
    """(per set, pooled, pooled paired) figures of the played ``results`` (set id -> policy ->
    EpisodeResult list), printed as they are made (unless --quiet)."""
    from ..radbench.results import paired, summarize

    max_steps = sets[0].max_steps
    others = [p for p in policies if p != reference]
    per_set = {}
    for s in sets:
        figures = {p: summarize(results[s.id][p], max_steps) for p in policies}
        comparisons = {p: paired(results[s.id][p], results[s.id][reference], max_steps) for p in others}
        per_set[s.id] = {"sha256": s.sha256, "episodes": len(s.episodes), "policies": figures,
                         "paired": comparisons}
        _say(args, f"{s.id} (sha256 {s.sha256[:16]}):")
        for p in policies:
            _say(args, f"  {p:<12} {_fmt(figures[p])}")
    groups: dict[str, list[str]] = {"all": [s.id for s in sets]}
    for count in sorted({s.obstructions for s in sets}):
        groups[f"obs{count}"] = [s.id for s in sets if s.obstructions == count]
    for name in [n for n in ("low", "medium", "high") if any(s.snr == n for s in sets)]:
        groups[name] = [s.id for s in sets if s.snr == name]
    pooled, pooled_pairs = {}, {}
    for label, keys in groups.items():
        pool = _pool(results, keys)
        pooled[label] = {p: summarize(pool[p], max_steps) for p in policies}
        pooled_pairs[label] = {p: paired(pool[p], pool[reference], max_steps) for p in others}
    _say(args, "pooled:")
    for label in groups:
        for p in policies:
            _say(args, f"  {label:<7} {p:<12} {_fmt(pooled[label][p])}")
    for p in others:
        c = pooled_pairs["all"][p]
        half = c["mean_diff_ci95"]
        _say(args, f"paired, all sets: {p} - {reference}: mean {c['mean_diff']:+.2f} "
                   f"± {'-' if half is None else f'{half:.2f}'} moves, wins {c['wins']} losses {c['losses']} "
                   f"ties {c['ties']} (sign test p = {c['sign_test_p']:.3g})")
    return per_set, pooled, pooled_pairs


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from ..radbench.sets import SetFileError

    try:
        if args.list:
            return _list(args)
        if args.generate is not None:
            return _generate(args)
        if args.cost:
            return _cost(args)
        return _play(args)
    except (SetFileError, ValueError) as exc:
        print(f"medc-radbench: {exc}", file=sys.stderr)
        return 2


def _cost(args: argparse.Namespace) -> int:
    import torch

    from ..radbench.cost import decision_cost
    from ..radbench.physics import prior_of
    from ..radbench.play import resolve_policy
    from ..radbench.sets import load_sets

    torch.set_num_threads(args.threads)
    grid, agents = args.grid or 20, args.agents or 1
    policies = list(args.policies) or list(QUICK["policies"])
    (bench_set,) = load_sets(grid, agents, obstructions=[3], snrs=["medium"])
    bundles = {p: resolve_policy(p)[0] for p in policies}
    team = _team_model(bundles, args.prior_background)
    out = {}
    big = f"b{args.batch}"
    _say(args, f"medc-radbench --cost: {bench_set.id} of grid {grid}, {agents} agent(s), one torch thread "
               f"({args.threads}); ms per call p50/p99, decisions (one agent's move) per second"
               + _model_words(team) + ("" if args.endgame is None else f"; bundles with the endgame at "
                                                                         f"tau {args.endgame:g}"))
    for policy in policies:
        c = decision_cost(bench_set, bundles[policy] or policy, batch=args.batch, runtime=args.runtime,
                          sensing=team, endgame=args.endgame)
        out[str(policy)] = c
        label = f"node ({c['node_runtime']})" if "node_runtime" in c else "node"
        node = f"{label} {c['node_ms_p50']}/{c['node_ms_p99']} ms, " if "node_ms_p50" in c else ""
        if "endgame_ms_p50" in c:
            node += (f"the endgame planned {c['endgame_decisions']} of them at {c['endgame_ms_p50']}/"
                     f"{c['endgame_ms_p99']} ms, ")
        terms = c["likelihood_terms_per_decision"]
        work = (f"{terms:,} likelihood terms" if terms
                else f"{c['macs_per_decision']:,.0f} MACs" if "macs_per_decision" in c else "")
        _say(args, f"  {str(policy)[-40:]:<40} B=1 {c['b1']['call_ms_p50']}/{c['b1']['call_ms_p99']} ms "
                   f"({c['b1']['decisions_per_s']:,.0f}/s), B={args.batch} {c[big]['call_ms_p50']} ms "
                   f"({c[big]['decisions_per_s']:,.0f}/s), {node}{work}")
    print(json.dumps({"benchmark": "medc-radbench", "cost": out, "set": bench_set.id,
                      "set_sha256": bench_set.sha256, "grid": grid, "agents": agents,
                      "threads": args.threads, "team_sensing": team.to_dict(), "endgame": args.endgame,
                      "background_prior": prior_of(team)}))
    return 0


def _model_words(team) -> str:
    """The header's words for a team model other than the nominal one ('' for it)."""
    from ..radbench.physics import prior_of

    if prior_of(team) is None:
        return ""
    return (f"; the estimator's background prior {team.background[0]:g}-{team.background[1]:g} counts/s "
            f"at {team.levels[1]} levels")


def _episodes_file(path: Path | None, overwrite: bool):
    """Where ``--out``'s episodes go: nowhere without it; else a fresh temporary file beside it,
    moved into place when every set is played (never written through a link; what is already there
    replaced only with ``--overwrite``; a folder, a device or a name too long refused before any
    episode is played)."""
    from ..outfiles import AtomicOutput, check_output

    if path is None:
        return contextlib.nullcontext()
    return AtomicOutput(check_output(path, overwrite=overwrite), overwrite=overwrite)


def _line(record: dict) -> bytes:
    return (json.dumps(record) + "\n").encode()


def _play_sets(args: argparse.Namespace, grid: int, agents: int, counts, snrs, episodes: int | None
               ) -> tuple[list, str]:
    """(the sets to play, where they come from): ``--sets-file``'s (ValueError when ``--grid`` or
    ``--agents`` disagree with it) or the committed file of ``grid`` and ``agents``; ``episodes`` of
    each from its episode ``--first`` when either is given."""
    from ..radbench.sets import file_name, load_sets

    if args.sets_file is not None:
        sets = load_sets(path=args.sets_file, sha256=args.sha256, obstructions=counts, snrs=snrs)
        source = str(args.sets_file)
        if (args.grid and args.grid != sets[0].grid) or (args.agents and args.agents != sets[0].agents):
            raise ValueError(f"--grid/--agents do not match the set file's (grid {sets[0].grid}, "
                             f"{sets[0].agents} agent(s))")
    else:
        sets = load_sets(grid, agents, obstructions=counts, snrs=snrs)
        source = file_name(grid, agents)
    if episodes is not None or args.first:
        sets = [s.part(args.first, episodes) for s in sets]
    return sets, source


def _team_model(bundles: dict[str, Any], prior: str | None):
    """The team's model every policy of one run plays under: ``prior`` (``--prior-background``) over
    :data:`~medc_training.radbench.physics.TEAM_SENSING` when given, else the background prior the
    bundles record when every policy is a bundle recording the same one, else the nominal model.
    ``bundles``: each policy's loaded bundle (None: a controller). Raises ValueError when the policies
    would need different models."""
    from medc_training.bundle import manifest_prior

    from ..radbench.physics import team_sensing

    if prior is not None:
        return team_sensing(prior)
    own = {p: None if b is None else manifest_prior(b.manifest) for p, b in bundles.items()}
    priors = set(own.values())
    if len(priors) > 1:
        shown = ", ".join(f"{p if len(p) <= 60 else '...' + p[-57:]}: "
                          + ("the model's" if v is None else f"{v[0]:g}-{v[1]:g} at {v[2]}")
                          for p, v in own.items())
        raise ValueError(f"the policies of one run share the team's model, but their background priors "
                         f"differ ({shown}); play them in separate runs, or give --prior-background to "
                         "play every one under it")
    return team_sensing(priors.pop())


def _play(args: argparse.Namespace) -> int:
    import torch

    from ..console import progress_bar
    from ..radbench.departure import Departure
    from ..radbench.pairing import episode_record
    from ..radbench.play import play_set, policy_names, resolve_policy

    if args.threads < 1 or args.batch < 1 or (args.episodes is not None and args.episodes < 1):
        raise ValueError("--threads, --batch and --episodes must be positive")
    torch.set_num_threads(args.threads)
    departure = Departure.parse(args.departure)
    if args.quick:
        grid, agents, counts, snrs = QUICK["grid"], QUICK["agents"], QUICK["obstructions"], QUICK["snrs"]
        episodes = QUICK["episodes"]
        policies = list(args.policies) or list(QUICK["policies"])
    else:
        grid, agents = args.grid or 20, args.agents or 1
        counts, snrs, episodes = args.obstructions, args.snr, args.episodes
        policies = list(args.policies) or list(QUICK["policies"])
    if len(set(policies)) != len(policies):
        raise ValueError("a policy is named twice")
    reference = args.reference or policies[0]
    if reference not in policies:
        raise ValueError(f"--reference {reference!r} is not one of the policies played")
    sets, source = _play_sets(args, grid, agents, counts, snrs, episodes)
    # Each bundle is loaded and checked once for the whole run, not once per set.
    bundles = {p: resolve_policy(p)[0] for p in policies}
    team = _team_model(bundles, args.prior_background)
    played_as = {p: bundles[p] or p for p in policies}
    if args.endgame is not None:
        from ..radbench.endgame import Endgame

        if args.temperature:
            raise ValueError("--endgame is a rule on the greedy team: give it without --temperature")
        played_as.update({p: Endgame(b, args.endgame) for p, b in bundles.items() if b is not None})
    grid, agents, file_digest = sets[0].grid, sets[0].agents, sets[0].file_sha256
    max_steps = sets[0].max_steps
    _say(args, f"medc-radbench: {source} (sha256 {file_digest}), grid {grid} x {grid} cells of "
               f"{sets[0].cell_m:g} m, {agents} agent(s), {len(sets)} set(s) x {len(sets[0].episodes)} "
               f"episodes, policies {', '.join(policies)}"
               + ("" if departure.nominal else f"; the world departs from the model: {departure.to_dict()}")
               + _model_words(team)
               + ("" if args.endgame is None else f"; bundles with the endgame at tau {args.endgame:g}"))
    results: dict[str, dict[str, list]] = {s.id: {} for s in sets}
    seconds = dict.fromkeys(policies, 0.0)
    total = len(policies) * sum(len(s.episodes) for s in sets)
    names = policy_names()  # the rest are bundles, which --temperature applies to
    with (_episodes_file(args.out, args.overwrite) as out,
          progress_bar(total, unit="episode", disable=args.quiet) as bar):
        for s in sets:
            for policy in policies:
                start = time.perf_counter()
                played = play_set(s, played_as[policy], batch=args.batch, device=args.device,
                                  run=args.run, sensing=team,
                                  progress=bar.update, departure=departure, temperature=args.temperature)
                seconds[policy] += time.perf_counter() - start
                results[s.id][policy] = played
                if out is not None:
                    extra = {**({"departure": departure.to_dict()} if not departure.nominal else {}),
                             **({"endgame": args.endgame} if args.endgame is not None and bundles[policy]
                                else {}),
                             **({"temperature": args.temperature}
                                if args.temperature and policy not in names else {})}
                    for r in played:
                        out.file.write(_line(episode_record(policy, s, r, args.run, **extra)))
    per_set, pooled, pooled_pairs = _report(args, sets, results, policies, reference)
    print(json.dumps({
        "benchmark": "medc-radbench", "grid": grid, "cell_m": sets[0].cell_m, "agents": agents,
        "max_steps": max_steps,
        "set_file": source, "set_file_sha256": file_digest, "quick": bool(args.quick), "run": args.run,
        "episodes_per_set": len(sets[0].episodes), "policies": policies, "reference": reference,
        "team_sensing": team.to_dict(), "departure": departure.to_dict(),
        "temperature": args.temperature, "endgame": args.endgame,
        "seconds": {p: round(v, 2) for p, v in seconds.items()},
        "sets": per_set, "pooled": pooled, "paired_pooled": pooled_pairs,
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
