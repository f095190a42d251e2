"""Which target-localization observation does MDRL-sparse learn from? A small, resumable probe.

    python -m medc_lab.cli.observation_probe --out docs/reproduction/observation-probe \
        --variants maps,maps+estimate,ego6,ego6+estimate --arch mlp --steps 300000 --seeds 0

Each (variant, architecture, seed) is one MDRL-sparse run at the CPU scale (medc_training.config
CPU_SCALE) on A3W2 unless told otherwise, written to OUT/<variant>-<arch>/seed<k>/ (metrics.csv,
summary.json); a finished run is skipped, so an interrupted probe resumes. The last line printed is
JSON: per run, the greedy evaluation episode length at the start (mean of the first three
evaluations) and at the end (mean of the last three), their ratio, the agents' own training
episode length, and training steps per second.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path


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
    from medc_training.metrics import read_metrics

    from ..report_plots import plot_methods

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
    """Train one probe run (skipped when finished) and return its curve summary."""
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
