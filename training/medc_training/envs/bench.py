"""`medc-bench env`: agent-steps per second of the batched core vs. one ParallelEnv at a time.

Scenario (issue 2): target localization A3W2 on a 30×30 grid, B=256 environments.

- batched: ``make_batched(..., num_envs=B)`` stepped with random valid moves (sampled from
  the mask each step, included in the time), observations built every step, auto-resets
  included. Measured with ``copy_obs=False`` (the observation buffer the core updates in
  place, what a rollout loop that copies into its own storage uses) and with
  ``copy_obs=True`` (a fresh observation tensor per step).
- one by one: B separate ``make_env`` ParallelEnvs, each stepped in turn through the
  PettingZoo API with random valid moves from the action masks, reset when done.

Agent-steps = environment steps × agents. Torch runs on one intra-op thread by default
(``--threads``): the per-step tensors are small, and on a shared 2-core machine a second
thread costs more in synchronisation than it gains. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from medc_training.envs import make_batched, make_env


def _batched_rate(args: argparse.Namespace, copy_obs: bool) -> float:
    env = make_batched(
        "target_localization",
        num_envs=args.num_envs,
        device=args.device,
        seed=args.seed,
        agents=args.agents,
        walls=args.walls,
        grid=args.grid,
        max_steps=100,
        copy_obs=copy_obs,
    )
    gen = torch.Generator(device=env.device).manual_seed(args.seed)
    _, mask = env.reset()
    b, n, a = mask.shape

    def run(steps: int) -> None:
        nonlocal mask
        for _ in range(steps):
            actions = torch.multinomial(mask.view(-1, a).float(), 1, generator=gen).view(b, n)
            mask = env.step(actions).mask

    run(args.warmup)
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    run(args.steps)
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    return args.steps * b * n / (time.perf_counter() - start)


def _one_by_one_rate(args: argparse.Namespace) -> float:
    envs = [
        make_env(
            "target_localization", seed=args.seed + i, agents=args.agents, walls=args.walls, grid=args.grid
        )
        for i in range(args.num_envs)
    ]
    rng = np.random.default_rng(args.seed)
    obs = [e.reset()[0] for e in envs]

    def run(steps: int) -> int:
        agent_steps = 0
        for _ in range(steps):
            for i, env in enumerate(envs):
                acts = {}
                for agent in env.agents:
                    allowed = np.flatnonzero(obs[i][agent]["action_mask"])
                    acts[agent] = int(rng.choice(allowed))
                obs[i], *_ = env.step(acts)
                agent_steps += len(acts)
                if not env.agents:
                    obs[i] = env.reset()[0]
        return agent_steps

    run(1)
    start = time.perf_counter()
    agent_steps = run(args.one_by_one_steps)
    return agent_steps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="medc-bench env", description=__doc__.split("\n\n")[0])
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=30)
    p.add_argument("--steps", type=int, default=400, help="timed batched steps")
    p.add_argument("--warmup", type=int, default=50, help="untimed batched steps first")
    p.add_argument(
        "--one-by-one-steps", type=int, default=10, help="timed steps of each of the B ParallelEnvs"
    )
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(
        f"target localization A{args.agents}W{args.walls}, {args.grid}x{args.grid}, B={args.num_envs}, "
        f"device={args.device}, torch threads={args.threads}"
    )
    batched = _batched_rate(args, copy_obs=False)
    print(f"batched core (in-place observation buffer): {batched:12,.0f} agent-steps/s")
    batched_copy = _batched_rate(args, copy_obs=True)
    print(f"batched core (fresh observation tensors):   {batched_copy:12,.0f} agent-steps/s")
    one = _one_by_one_rate(args)
    print(f"one by one through the ParallelEnv API:     {one:12,.0f} agent-steps/s")
    ratio = batched / one
    print(f"ratio batched / one by one:                 {ratio:12.1f}x")
    print(
        json.dumps(
            {
                "batched_agent_steps_per_s": round(batched),
                "batched_copy_obs_agent_steps_per_s": round(batched_copy),
                "one_by_one_agent_steps_per_s": round(one),
                "ratio": round(ratio, 1),
                "num_envs": args.num_envs,
                "agents": args.agents,
                "walls": args.walls,
                "grid": args.grid,
                "device": args.device,
                "threads": args.threads,
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
