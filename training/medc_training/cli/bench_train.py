"""`medc-bench train`: training throughput and the RS / sparse wall-time ratio.

Prints environment steps per second and PPO updates per second for the CPU scale (A3W2,
sparse and RS), the RS/sparse wall-time ratio over the same number of training steps, and,
when ``torch.cuda.is_available()``, the same figures on CUDA at the paper scale (G = 30).
The last line is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from ..config import scaled_config
from ..ppo import Trainer


def measure(scale: str, method: str, updates: int, device: str, warmup: int = 1, **overrides) -> dict:
    """Run ``warmup`` + ``updates`` PPO updates and time the last ``updates`` of them."""
    cfg = scaled_config(scale, method=method, device=device, total_steps=10**12, **overrides)
    trainer = Trainer(cfg)
    for _ in range(warmup):
        trainer.train_update()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    collect_s = update_s = 0.0
    steps = 0
    for _ in range(updates):
        t0 = time.perf_counter()
        before = trainer.global_step
        trainer.collect()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t1 = time.perf_counter()
        trainer.update()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t2 = time.perf_counter()
        collect_s += t1 - t0
        update_s += t2 - t1
        steps += trainer.global_step - before
    total = collect_s + update_s
    return {
        "scale": scale, "method": method, "device": device, "grid": cfg.grid, "agents": cfg.agents,
        "walls": cfg.walls, "num_envs": cfg.num_envs, "horizon": cfg.steps_per_update, "epochs": cfg.epochs,
        "updates": updates, "env_steps_per_s": steps / total, "updates_per_s": updates / total,
        "collect_steps_per_s": steps / collect_s, "wall_s": total,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="medc-bench train", description=__doc__.split("\n\n")[0])
    p.add_argument("--updates", type=int, default=4, help="timed PPO updates per measurement (default 4)")
    p.add_argument("--cuda-updates", type=int, default=2, help="timed updates at paper scale on CUDA")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    result: dict = {"torch_threads": torch.get_num_threads()}
    sparse = measure("cpu", "sparse", args.updates, "cpu", agents=3, walls=2)
    rs = measure("cpu", "rs", args.updates, "cpu", agents=3, walls=2)
    for tag, r in (("cpu_sparse", sparse), ("cpu_rs", rs)):
        print(f"{tag}: {r['env_steps_per_s']:.0f} env steps/s, {r['updates_per_s']:.3f} updates/s "
              f"(grid {r['grid']}, A{r['agents']}W{r['walls']}, {r['num_envs']} envs, "
              f"horizon {r['horizon']}, "
              f"{r['epochs']} epochs; rollout alone {r['collect_steps_per_s']:.0f} steps/s)")
        result[tag] = r
    result["rs_over_sparse_wall_time"] = rs["wall_s"] / sparse["wall_s"]
    print(f"RS / sparse wall time for the same training steps: {result['rs_over_sparse_wall_time']:.3f} "
          "(the paper reports 2x)")
    if torch.cuda.is_available():
        for method in ("sparse", "rs"):
            r = measure("paper", method, args.cuda_updates, "cuda", agents=3, walls=2)
            print(f"cuda_{method} (paper scale): {r['env_steps_per_s']:.0f} env steps/s, "
                  f"{r['updates_per_s']:.3f} updates/s")
            result[f"cuda_{method}"] = r
        ratio = result["cuda_rs"]["wall_s"] / result["cuda_sparse"]["wall_s"]
        result["cuda_rs_over_sparse_wall_time"] = ratio
    else:
        print("CUDA: not available on this machine (no figures)")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
