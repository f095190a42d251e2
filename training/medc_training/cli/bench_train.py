"""`medc-bench train`: the default learner's training throughput on both sensing presets; RS / sparse.

Prints training steps per second (environment steps of the whole team, rollout and PPO update
together) and PPO updates per second of the CPU-scale learner (``config.CPU_SCALE``) on A3W2 for:

- ``sparse``: the default learner (the CPU scale's architecture on the default observation, the
  source estimate included), MDRL-sparse, paper-simple sensing on the CPU scale's 13×13 grid;
- ``rs``: the same with BFS reward shaping (the RS/sparse wall-time ratio);
- ``baseline_maps_mlp``: the learner before observation variants (the paper's 5 absolute maps,
  MLP), measured in the same run: ``speedup_over_baseline`` is sparse / baseline;
- ``lenet5``: the paper's LeNet-5 on the default observation;
- ``realistic_sparse``: the default learner on the realistic sensing preset (unknown strength and
  background, Poisson counts, walls block the line of sight) on 20×20 with 100-step episodes, and
  ``realistic_baseline_maps_mlp`` the maps/MLP baseline there: ``realistic_speedup_over_baseline``
  is their ratio, ``realistic_over_simple`` realistic_sparse / sparse (``--no-realistic`` skips them);
- ``realistic40_sparse``: the default learner on the realistic preset at the claims scale's 40×40 with
  50-step episodes.

A/B against the estimator path the fused one replaced, in the same run: each default learner also
runs as ``..._reference`` (``reference`` path, :data:`~medc_training.envs.tl_observation.ESTIMATOR_PATHS`),
and ``..._speedup_over_reference`` is their ratio of training steps per second (``--no-reference``
skips them), and as ``..._kernel1``: the estimator's native kernel on one thread instead of splitting
each call's episodes over :func:`~medc_training.envs.tl_native.threads`; ``..._speedup_over_kernel1``
is the split's A/B (when the kernel has more than one thread; ``--no-split-ab`` skips them).
``--thread-ab`` adds the default realistic learners on one torch thread beside the run's count
(``..._1thread``; on two threads, ``..._2threads``, when the run is on one), which says whether the
second core pays. ``--only-ab`` times only the default learners and their twins.

Rounds are interleaved, one update of each learner per round, so that a shared machine's load
hits all alike; medians are reported. When ``torch.cuda.is_available()`` the sparse/RS figures are
also measured on CUDA at the paper scale (G = 30). The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import statistics
import time

import torch

from ..config import scaled_config
from ..envs import tl_native
from ..envs.tl_observation import estimator_path
from ..envs.tl_sensing import DEFAULT_SENSING
from ..ppo import Trainer
from .bench_env import loadavg

#: The realistic preset's scenario: RAD-A2C's 20 m x 20 m area, 1 m cells, 100-step episodes.
REALISTIC = {"grid": 20, "max_steps": 100, "env_options": {"sensing": "realistic"}}
#: The claims scale's realistic scenario (config.CLAIMS_SCALE): 40×40 cells, 50-step episodes.
REALISTIC_40 = {"grid": 40, "max_steps": 50, "env_options": {"sensing": "realistic"}}
#: Learner options of this benchmark only (not TrainConfig fields): the estimator path, the torch
#: threads it runs on (0: the process's count) and the native kernel's threads (0: tl_native.threads()).
_PATH, _THREADS, _KERNEL = "_path", "_threads", "_kernel"


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


def measure(scale: str, learners: dict[str, dict], rounds: int, device: str, **overrides) -> dict[str, dict]:
    """Time ``rounds`` updates of each learner (label -> config overrides, e.g. {"method": "rs"}),
    interleaved round by round so that a shared machine's changing load hits every learner alike;
    per-update medians are reported."""
    trainers, threads, kernel = {}, {}, {}
    default_threads = torch.get_num_threads()
    for m, extra in learners.items():
        extra = dict(extra)
        path, threads[m] = extra.pop(_PATH, "fused"), extra.pop(_THREADS, 0) or default_threads
        kernel[m] = extra.pop(_KERNEL, 0)
        with estimator_path(path):
            cfg = scaled_config(scale, device=device, total_steps=10**12, **{**overrides, **extra})
            trainers[m] = Trainer(cfg)
    methods = tuple(learners)
    cuda = device.startswith("cuda")

    def timed(m: str) -> tuple[float, float, int]:
        torch.set_num_threads(threads[m])
        try:
            with tl_native.split(kernel[m]) if kernel[m] else contextlib.nullcontext():
                return _timed_update(trainers[m], cuda)
        finally:
            torch.set_num_threads(default_threads)

    for m in methods:  # warm-up (allocations, first-call overheads)
        timed(m)
    times: dict[str, list[tuple[float, float, int]]] = {m: [] for m in methods}
    for _ in range(rounds):
        for m in methods:
            times[m].append(timed(m))
    results = {}
    for m, rows in times.items():
        cfg = trainers[m].cfg
        total = statistics.median(c + u for c, u, _ in rows)
        collect = statistics.median(c for c, _, _ in rows)
        steps = rows[0][2]
        results[m] = {
            "scale": scale, "method": cfg.method, "sensing": cfg.env_options.get("sensing", DEFAULT_SENSING),
            "max_steps": cfg.max_steps, "device": device, "grid": cfg.grid, "agents": cfg.agents,
            "walls": cfg.walls, "observation": cfg.observation, "num_envs": cfg.num_envs,
            "horizon": cfg.steps_per_update,
            "epochs": cfg.epochs, "arch": cfg.arch, "rounds": rounds,
            "estimator": learners[m].get(_PATH, "fused"), "threads": threads[m],
            "kernel_threads": kernel[m] or _kernel_threads(threads[m]),
            "env_steps_per_s": steps / total, "updates_per_s": 1.0 / total,
            "collect_steps_per_s": steps / collect, "median_update_s": total,
        }
    return results


def main(argv: list[str] | None = None) -> int:
    from ..console import HelpFormatter

    p = argparse.ArgumentParser(prog="medc-bench train", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--updates", type=int, default=5, help="timed rounds (one update per method each)")
    p.add_argument("--cuda-updates", type=int, default=2, help="timed updates at paper scale on CUDA")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    p.add_argument("--no-realistic", action="store_true", help="skip the realistic-preset learners")
    p.add_argument("--no-reference", action="store_true",
                   help="skip the A/B learners on the reference estimator")
    p.add_argument("--no-split-ab", action="store_true",
                   help="skip the A/B learners with the native kernel on one thread")
    p.add_argument("--thread-ab", action="store_true",
                   help="also run the default realistic learners on one torch thread (two if --threads 1)")
    p.add_argument("--only-ab", action="store_true",
                   help="only the default learners and their A/B (no RS, LeNet-5 or maps baselines)")
    p.add_argument("--horizon", type=int, default=0,
                   help="training steps per CPU update (0: the CPU scale's; small for quick checks)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    result: dict = {"torch_threads": torch.get_num_threads(), "native_kernel": tl_native.usable(),
                    "kernel_threads": _kernel_threads(torch.get_num_threads()), "load_average": loadavg()}
    load = " ".join(map(str, result["load_average"]))
    print(f"medc-bench train: torch threads {result['torch_threads']}, kernel threads "
          f"{result['kernel_threads']}, load average {load}; estimator: {tl_native.status()}")
    learners = _learners(args)
    cpu = measure("cpu", learners, args.updates, "cpu", agents=3, walls=2,
                  **({"horizon": args.horizon} if args.horizon else {}))
    for m, r in cpu.items():
        print(f"cpu_{m}: {r['env_steps_per_s']:.0f} training steps/s, {r['updates_per_s']:.3f} updates/s "
              f"({r['sensing']}, grid {r['grid']}, {r['max_steps']} steps, A{r['agents']}W{r['walls']}, "
              f"{r['method']}, "
              f"observation {r['observation']}, "
              f"{r['arch']}, {r['num_envs']} envs, horizon {r['horizon']}, {r['epochs']} epochs; "
              f"rollout alone {r['collect_steps_per_s']:.0f} steps/s)")
        result[f"cpu_{m}"] = r
    _ab_ratios(cpu, result)
    if args.only_ab:
        print(json.dumps(result))
        return 0
    result["speedup_over_baseline"] = (cpu["sparse"]["env_steps_per_s"]
                                       / cpu["baseline_maps_mlp"]["env_steps_per_s"])
    print(f"default learner / baseline (maps, mlp) training steps/s: {result['speedup_over_baseline']:.2f}")
    if not args.no_realistic:
        result["realistic_speedup_over_baseline"] = (cpu["realistic_sparse"]["env_steps_per_s"]
                                                     / cpu["realistic_baseline_maps_mlp"]["env_steps_per_s"])
        result["realistic_over_simple"] = (cpu["realistic_sparse"]["env_steps_per_s"]
                                           / cpu["sparse"]["env_steps_per_s"])
        print(f"realistic: default learner / baseline (maps, mlp) training steps/s: "
              f"{result['realistic_speedup_over_baseline']:.2f}")
        print(f"default learner, realistic 20x20 / paper-simple 13x13 training steps/s: "
              f"{result['realistic_over_simple']:.2f}")
    result["rs_over_sparse_wall_time"] = cpu["rs"]["median_update_s"] / cpu["sparse"]["median_update_s"]
    print(f"RS / sparse wall time per update (median of {args.updates} interleaved rounds): "
          f"{result['rs_over_sparse_wall_time']:.3f} (the paper reports 2x)")
    if torch.cuda.is_available():
        gpu = measure("paper", {"sparse": {}, "rs": {"method": "rs"}}, args.cuda_updates, "cuda",
                      agents=3, walls=2)
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


def _learners(args: argparse.Namespace) -> dict[str, dict]:
    """The learners to time, label -> config overrides (and this benchmark's _PATH, _THREADS)."""
    default = {"sparse": {}}
    if not args.no_realistic:
        default.update(realistic_sparse=copy.deepcopy(REALISTIC),
                       realistic40_sparse=copy.deepcopy(REALISTIC_40))
    learners = dict(default)
    if not args.only_ab:
        learners.update(rs={"method": "rs"}, baseline_maps_mlp={"observation": "maps", "arch": "mlp"},
                        lenet5={"arch": "lenet5"})
        if not args.no_realistic:
            learners["realistic_baseline_maps_mlp"] = {**copy.deepcopy(REALISTIC), "observation": "maps",
                                                       "arch": "mlp"}
    for m, extra in default.items():
        if not args.no_reference:
            learners[f"{m}_reference"] = {**copy.deepcopy(extra), _PATH: "reference"}
        if not args.no_split_ab and tl_native.threads() > 1 and tl_native.usable():
            learners[f"{m}_kernel1"] = {**copy.deepcopy(extra), _KERNEL: 1}
        if args.thread_ab and m != "sparse":
            other = _other_threads(count=True)
            learners[f"{m}_{_other_threads()}"] = {**copy.deepcopy(extra), _THREADS: other}
    return learners


def _kernel_threads(torch_threads: int) -> int:
    """The native kernel's threads when torch runs on ``torch_threads`` (tl_native.threads())."""
    before = torch.get_num_threads()
    torch.set_num_threads(torch_threads)
    try:
        return tl_native.threads()
    finally:
        torch.set_num_threads(before)


def _other_threads(count: bool = False) -> int | str:
    """The thread count --thread-ab compares with (one thread, or two when the run is on one), as a
    number or as the learner's label suffix."""
    k = 2 if torch.get_num_threads() == 1 else 1
    return k if count else f"{k}thread" + ("s" if k > 1 else "")


def _ab_ratios(cpu: dict[str, dict], result: dict) -> None:
    """Print and record each default learner's training steps/s over its reference and 1-thread twins."""
    threads = f"{torch.get_num_threads()} / {_other_threads(count=True)} threads"
    kernel = f"kernel on {tl_native.threads()} threads / 1"
    for m in ("sparse", "realistic_sparse", "realistic40_sparse"):
        for twin, label in (("reference", "fused / reference estimator"), (_other_threads(), threads),
                            ("kernel1", kernel)):
            if m in cpu and f"{m}_{twin}" in cpu:
                a, b = cpu[m], cpu[f"{m}_{twin}"]
                ratio = a["env_steps_per_s"] / b["env_steps_per_s"]
                rollout = a["collect_steps_per_s"] / b["collect_steps_per_s"]
                result[f"{m}_speedup_over_{twin}"] = ratio
                print(f"A/B {m} ({a['sensing']} {a['grid']}x{a['grid']}), {label}: {ratio:.2f}x training "
                      f"steps/s ({a['env_steps_per_s']:.0f} vs {b['env_steps_per_s']:.0f}), rollout alone "
                      f"{rollout:.2f}x ({a['collect_steps_per_s']:.0f} vs {b['collect_steps_per_s']:.0f})")


if __name__ == "__main__":
    raise SystemExit(main())
