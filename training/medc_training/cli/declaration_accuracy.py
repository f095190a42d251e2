"""``python -m medc_training.cli.declaration_accuracy POLICY``: how well the team's declaration says
where the source is (:mod:`medc_training.declaration_eval`) on fixed episodes: the declared cell's
distance to the source and the steps to it, per end rule and noise."""

from __future__ import annotations

import argparse
import json

from ..declaration_eval import (
    END_RULES,
    add_episode_arguments,
    declaration_episodes,
    study_policy,
    study_team,
    summarize,
)
from ..envs import make_batched
from ..envs.names import TARGET_LOCALIZATION
from ..envs.tl_estimate import DEFAULT_THRESHOLD


def main(argv: list[str] | None = None) -> int:
    """One JSON line per (end rule, noise)."""
    p = argparse.ArgumentParser(prog="python -m medc_training.cli.declaration_accuracy",
                                description="Measure the team's declaration (the source localised) on fixed "
                                            "episodes: declared cell's distance to the source, steps to it.")
    add_episode_arguments(p, episodes=256)
    p.add_argument("--noise", choices=("off", "on", "both"), default="both",
                   help="paper-simple readings without / with Poisson noise (realistic always counts them)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD)
    args = p.parse_args(argv)
    bundle, attrs = study_team(args)
    sensing = attrs.get("sensing", "paper-simple")
    choices = {"off": [False], "on": [True], "both": [False, True]}
    noises = [None] if sensing != "paper-simple" else choices[args.noise]
    for rule in args.rule or list(END_RULES):
        for noise in noises:
            options = dict(attrs, posterior=True, end_on_find=rule == "either")
            if noise is not None:
                options["noise"] = noise
            env = make_batched(TARGET_LOCALIZATION, num_envs=args.envs, seed=args.seed, **options)
            rows = declaration_episodes(env, study_policy(args.policy, bundle, env), episodes=args.episodes,
                                        seed=args.seed, radius=args.radius, threshold=args.threshold)
            radius = args.radius if args.radius is not None else env.sensing.success_radius
            print(json.dumps({"policy": args.policy, "rule": rule, "noise": env.noise,
                              "sensing": env.sensing.name, "radius": radius, "threshold": args.threshold,
                              **env.attributes, **summarize(rows)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
