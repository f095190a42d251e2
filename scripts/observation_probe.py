#!/usr/bin/env python
"""Which target-localization observation does MDRL-sparse learn from? A small, resumable probe.

    python scripts/observation_probe.py --out docs/reproduction/observation-probe \
        --variants maps,maps+estimate,ego6,ego6+estimate --arch mlp --steps 300000 --seeds 0

Each (variant, architecture, seed) is one MDRL-sparse run at the CPU scale (medc_training.config
CPU_SCALE) on A3W2 unless told otherwise, written to OUT/<variant>-<arch>/seed<k>/ (metrics.csv,
summary.json); a finished run is skipped, so an interrupted probe resumes. The last line printed is
JSON: per run, the greedy evaluation episode length at the start (mean of the first three
evaluations) and at the end (mean of the last three), their ratio, the agents' own training
episode length, and training steps per second.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from medc_training.envs.names import DEFAULT_APPLICATION


def curve_summary(metrics_csv: Path) -> dict:
    """start/end greedy length (mean of first/last three evaluations) and training lengths."""
    rows = list(csv.DictReader(metrics_csv.open()))
    lengths = [float(r["episode_length"]) for r in rows]
    train = [float(r["train_episode_length"]) for r in rows
             if r.get("train_episode_length") not in (None, "")]
    start, end = sum(lengths[:3]) / 3, sum(lengths[-3:]) / 3
    return {"evaluations": len(rows), "greedy_start": round(start, 2), "greedy_end": round(end, 2),
            "end_over_start": round(end / start, 3) if start else None,
            "final_success_rate": float(rows[-1]["success_rate"]),
            "train_start": round(train[0], 2) if train else None,
            "train_end": round(sum(train[-3:]) / len(train[-3:]), 2) if train else None}


def plot_probe(out: Path) -> None:
    """OUT/probe.png: every variant's greedy evaluation curve (mean over its seeds, 95% band)."""
    from medc_lab.plots import plot_methods
    from medc_training.metrics import read_metrics

    series = {}
    for run in sorted(p for p in out.iterdir() if p.is_dir()):
        curves, steps = [], []
        for seed_dir in sorted(run.glob("seed*")):
            if (seed_dir / "summary.json").exists():
                rows = read_metrics(seed_dir / "metrics.csv")
                steps = steps if len(steps) >= len(rows) else [r["step"] for r in rows]
                curves.append([r["episode_length"] for r in rows])
        if curves:
            series[run.name] = (steps, curves)
    if series:
        plot_methods(series, out / "probe.png", "MDRL-sparse on each observation variant")


def run_one(job: dict) -> dict:
    import torch
    from medc_training.config import scaled_config
    from medc_training.ppo import Trainer
    from medc_training.runner import run_training

    torch.set_num_threads(1)
    out = Path(job["out"])
    if not (out / "summary.json").exists():
        cfg = scaled_config("cpu", **job["config"])
        run_training(Trainer(cfg), cfg, out, tensorboard=False, save_final=False)
        (out / "checkpoint.safetensors").unlink(missing_ok=True)
    summary = json.loads((out / "summary.json").read_text())
    result = {"run": job["name"], **curve_summary(out / "metrics.csv"),
              "steps_per_second": round(summary["steps"] / max(summary["train_seconds"], 1e-9), 1)}
    print(json.dumps(result), flush=True)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[1])
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
                if args.env != DEFAULT_APPLICATION:
                    from medc_training.cli import reproduce as r


                    cfg = {**cfg, **r.OTHER_EVAL, "env": args.env, "walls": 0, "grid": r.OTHER_GRID,
                           "max_steps": r.OTHER_MAX_STEPS,
                           "env_options": {**r.OTHER_APPS[args.env]["target"], "observation": variant}}
                    del cfg["observation"]
                if args.eval_every:
                    cfg["eval_every"] = args.eval_every
                if args.grid:
                    cfg["grid"] = args.grid
                if args.max_steps:
                    cfg["max_steps"] = args.max_steps
                if args.noise:
                    cfg["env_options"] = {**cfg.get("env_options", {}), "noise": True}
                short = "" if args.env == DEFAULT_APPLICATION else args.env.split("_")[0] + "-"
                name = f"{short}{variant}-{arch}" + ("-noise" if args.noise else "")
                jobs.append({"name": f"{name}/seed{seed}", "config": cfg,
                             "out": str(args.out / name / f"seed{seed}")})
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = list(pool.map(run_one, jobs))
    plot_probe(args.out)
    print(json.dumps({"probe": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
