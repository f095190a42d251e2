"""``python -m medc_lab.cli.calibrate TEAM``: the reliability study of the team's declarations
(:mod:`medc_lab.studies.calibration`) on fixed episodes, per end rule: the right rate per threshold
and by declared mass, printed as tables and appended as JSON lines to ``--out``."""

from __future__ import annotations

import argparse
import json
import time

import torch
from medc_training.declaration_eval import (
    END_RULES,
    add_episode_arguments,
    study_policy,
    study_team,
    threshold_episodes,
)
from medc_training.envs import make_batched
from medc_training.envs.names import TARGET_LOCALIZATION

from ..studies.calibration import THRESHOLDS, format_tables, reliability


def _pair(text: str, kind=float) -> list:
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected two comma-separated values, got {text!r}")
    return [kind(v) for v in parts]


def main(argv: list[str] | None = None) -> int:
    """The study per end rule, printed and (with ``--out``) appended as JSON."""
    p = argparse.ArgumentParser(prog="python -m medc_lab.cli.calibrate",
                                description="Reliability of the team's declarations on fixed episodes: "
                                            "the right rate per threshold and by declared mass.")
    add_episode_arguments(p, episodes=400)
    p.add_argument("--noise", choices=("off", "on"), default="on",
                   help="paper-simple readings without / with Poisson noise (realistic always counts them)")
    p.add_argument("--thresholds", type=lambda s: tuple(float(v) for v in s.split(",")), default=THRESHOLDS)
    p.add_argument("--levels", type=lambda s: _pair(s, int), default=None,
                   help="probe: NS,NB estimator levels")
    p.add_argument("--strength", type=_pair, default=None, help="probe: LO,HI source strength range")
    p.add_argument("--background", type=_pair, default=None, help="probe: LO,HI background range")
    p.add_argument("--line", choices=("sampled", "exact"), default=None, help="probe: line-of-sight rule")
    p.add_argument("--success-radius", type=float, default=None,
                   help="probe: the preset's success radius (cells), claimed and judged by a declaration")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="append one JSON record per configuration to this file")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    thresholds = tuple(sorted(args.thresholds))
    bundle, attrs = study_team(args)
    sensing = attrs.get("sensing", "paper-simple")
    probe = {key: value for key, value in (("levels", args.levels), ("strength", args.strength),
                                           ("background", args.background), ("line", args.line),
                                           ("success_radius", args.success_radius))
             if value is not None}
    if probe:
        base = sensing if isinstance(sensing, dict) else {"name": sensing}
        attrs["sensing"] = sensing = dict(base, **probe)
    name = sensing["name"] if isinstance(sensing, dict) else sensing
    for rule in args.rule or list(END_RULES):
        options = dict(attrs, posterior=True, end_on_find=rule == "either")
        if name == "paper-simple":
            options["noise"] = args.noise == "on"
        env = make_batched(TARGET_LOCALIZATION, num_envs=args.envs, seed=args.seed, **options)
        policy = study_policy(args.policy, bundle, env)
        steps: list = []
        start = time.perf_counter()
        rows = threshold_episodes(env, policy, episodes=args.episodes, seed=args.seed, radius=args.radius,
                                  thresholds=thresholds, step_masses=steps)
        study = reliability(rows, thresholds, steps)
        wrong = [{"threshold": t, "error": m["error"], "mass": m["mass"], "step": m["step"],
                  "strength": row["strength"], "background": row["background"]}
                 for row in rows for t, m in zip(thresholds, row["declarations"])
                 if m is not None and not m["correct"] and t == max(thresholds)]
        record = {"policy": args.policy, "rule": rule, "noise": env.noise,
                  "sensing_model": env.sensing.to_dict(),
                  "radius": args.radius if args.radius is not None else env.sensing.success_radius,
                  "seed": args.seed, **env.attributes, **study,
                  "wrong_at_highest": wrong, "seconds": round(time.perf_counter() - start, 1)}
        print(f"# {args.policy} {env.sensing.name} levels={list(env.sensing.levels)} grid={env.grid} "
              f"walls={env.attributes.get('walls')} rule={rule} noise={env.noise} episodes={args.episodes} "
              f"{' '.join(f'{k}={v}' for k, v in probe.items())} ({record['seconds']} s)")
        print(format_tables(study), flush=True)
        if args.out:
            with open(args.out, "a") as fh:
                fh.write(json.dumps(record) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
