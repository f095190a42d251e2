"""``python -m medc_lab.cli.observation_probe --out DIR``: the observation probe
(:mod:`medc_lab.probes.observation_views`): one MDRL-sparse run per (variant, architecture, seed), resumable;
the last line printed is JSON."""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from medc_training.envs.names import DEFAULT_APPLICATION

from ..catalogue import OTHER_APPS, OTHER_EVAL, OTHER_GRID, OTHER_MAX_STEPS
from ..probes import observation_views


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_lab.cli.observation_probe",
                                description=observation_views.__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--variants", default="maps,maps+estimate,ego6,ego6+estimate")
    p.add_argument("--arch", default="mlp", help="comma-separated architectures")
    p.add_argument("--steps", type=int, default=300_000)
    p.add_argument("--seeds", default="0", help="comma-separated seeds")
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=None, help="grid side (default: the CPU scale's)")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--noise", action="store_true", help="Poisson counting noise on the readings")
    p.add_argument("--env", default=DEFAULT_APPLICATION,
                   help="application; fleet_coordination / maze_cleaning use the reproduction's settings "
                        "(10x10, 400 steps, 3 agents, its target options, sampled evaluation) and take "
                        "'maps' or 'egoR'")
    p.add_argument("--eval-every", type=int, default=None)
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args(argv)
    jobs = []
    for variant in args.variants.split(","):
        for arch in args.arch.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                cfg = {"agents": args.agents, "walls": args.walls, "observation": variant, "arch": arch,
                       "total_steps": args.steps, "seed": seed, "method": "sparse"}
                if args.env in OTHER_APPS:
                    cfg = {**cfg, **OTHER_EVAL, "env": args.env, "walls": 0, "grid": OTHER_GRID,
                           "max_steps": OTHER_MAX_STEPS,
                           "env_options": {**OTHER_APPS[args.env]["target"], "observation": variant}}
                    del cfg["observation"]
                if args.eval_every:
                    cfg["eval_every"] = args.eval_every
                if args.grid:
                    cfg["grid"] = args.grid
                if args.max_steps:
                    cfg["max_steps"] = args.max_steps
                if args.noise:
                    cfg["env_options"] = {**cfg.get("env_options", {}), "noise": True}
                short = OTHER_APPS[args.env]["short"] + "-" if args.env in OTHER_APPS else ""
                name = f"{short}{variant}-{arch}" + ("-noise" if args.noise else "")
                jobs.append({"name": f"{name}/seed{seed}", "config": cfg,
                             "out": str(args.out / name / f"seed{seed}")})
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = list(pool.map(observation_views.run_one, jobs))
    observation_views.plot_probe(args.out)
    print(json.dumps({"probe": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
