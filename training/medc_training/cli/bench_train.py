"""`medc-bench train`: training throughput and the RS / sparse wall-time ratio.

Prints environment steps per second and PPO updates per second for the CPU scale (A3W2,
sparse and RS), the RS/sparse wall-time ratio over the same number of training steps, and,
when ``torch.cuda.is_available()``, the same figures on CUDA at the paper scale (G = 30).
The last line is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from ..config import scaled_config
from ..ppo import Trainer


def _timed_update(trainer: Trainer, cuda: bool) -> tuple[float, float, int]:
    """(collect seconds, update seconds, training steps) of one PPO update."""
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    sync()
    t0 = time.perf_counter()
    before = trainer.global_step
    trainer.collect()
    sync()
    t1 = time.perf_counter()
    trainer.update()
    sync()
    return t1 - t0, time.perf_counter() - t1, trainer.global_step - before


def measure(scale: str, methods: tuple[str, ...], rounds: int, device: str, **overrides) -> dict[str, dict]:
    """Time ``rounds`` updates of each method, interleaved round by round so that a shared
    machine's changing load hits every method alike; per-update medians are reported."""
    trainers = {m: Trainer(scaled_config(scale, method=m, device=device, total_steps=10**12, **overrides))
                for m in methods}
    cuda = device.startswith("cuda")
    for trainer in trainers.values():  # warm-up (allocations, first-call overheads)
        _timed_update(trainer, cuda)
    times: dict[str, list[tuple[float, float, int]]] = {m: [] for m in methods}
    for _ in range(rounds):
        for m, trainer in trainers.items():
            times[m].append(_timed_update(trainer, cuda))
    results = {}
    for m, rows in times.items():
        cfg = trainers[m].cfg
        total = statistics.median(c + u for c, u, _ in rows)
        collect = statistics.median(c for c, _, _ in rows)
        steps = rows[0][2]
        results[m] = {
            "scale": scale, "method": m, "device": device, "grid": cfg.grid, "agents": cfg.agents,
            "walls": cfg.walls, "num_envs": cfg.num_envs, "horizon": cfg.steps_per_update,
            "epochs": cfg.epochs, "arch": cfg.arch, "rounds": rounds,
            "env_steps_per_s": steps / total, "updates_per_s": 1.0 / total,
            "collect_steps_per_s": steps / collect, "median_update_s": total,
        }
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="medc-bench train", description=__doc__.split("\n\n")[0])
    p.add_argument("--updates", type=int, default=5, help="timed rounds (one update per method each)")
    p.add_argument("--cuda-updates", type=int, default=2, help="timed updates at paper scale on CUDA")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    result: dict = {"torch_threads": torch.get_num_threads()}
    cpu = measure("cpu", ("sparse", "rs"), args.updates, "cpu", agents=3, walls=2)
    for m, r in cpu.items():
        print(f"cpu_{m}: {r['env_steps_per_s']:.0f} env steps/s, {r['updates_per_s']:.3f} updates/s "
              f"(grid {r['grid']}, A{r['agents']}W{r['walls']}, {r['arch']}, {r['num_envs']} envs, "
              f"horizon {r['horizon']}, {r['epochs']} epochs; "
              f"rollout alone {r['collect_steps_per_s']:.0f} steps/s)")
        result[f"cpu_{m}"] = r
    result["rs_over_sparse_wall_time"] = cpu["rs"]["median_update_s"] / cpu["sparse"]["median_update_s"]
    print(f"RS / sparse wall time per update (median of {args.updates} interleaved rounds): "
          f"{result['rs_over_sparse_wall_time']:.3f} (the paper reports 2x)")
    if torch.cuda.is_available():
        gpu = measure("paper", ("sparse", "rs"), args.cuda_updates, "cuda", agents=3, walls=2)
        for m, r in gpu.items():
            print(f"cuda_{m} (paper scale): {r['env_steps_per_s']:.0f} env steps/s, "
                  f"{r['updates_per_s']:.3f} updates/s")
            result[f"cuda_{m}"] = r
        ratio = gpu["rs"]["median_update_s"] / gpu["sparse"]["median_update_s"]
        result["cuda_rs_over_sparse_wall_time"] = ratio
    else:
        print("CUDA: not available on this machine (no figures)")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
