"""`medc-bench env`: agent-steps per second of the batched core vs. one ParallelEnv at a time.

Scenario (issue 2): target localization A3W2 on a 30×30 grid, B=256 environments.

- batched: ``make_batched(..., num_envs=B)`` stepped with random valid moves (sampled from
  the mask each step, included in the time), observations built every step, auto-resets
  included. Measured with ``copy_obs=False`` (the observation buffer the core updates in
  place, what a rollout loop that copies into its own storage uses) and with
  ``copy_obs=True`` (a fresh observation tensor per step).
- one by one: B separate ``make_env`` ParallelEnvs, each stepped in turn through the
  PettingZoo API with random valid moves from the action masks, reset when done.

The paths are measured in interleaved rounds and the medians reported (the ratio is the
median of the per-round ratios), so that load from other jobs on a shared machine hits all
paths alike. Agent-steps = environment steps × agents. Torch runs on one intra-op thread by default
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


class _Batched:
    """A batched core stepped with random valid moves sampled from its mask."""

    def __init__(self, args: argparse.Namespace, copy_obs: bool) -> None:
        self.env = make_batched(
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
        self.gen = torch.Generator(device=self.env.device).manual_seed(args.seed)
        _, self.mask = self.env.reset()

    def rate(self, steps: int) -> float:
        b, n, a = self.mask.shape
        cuda = self.env.device.type == "cuda"
        if cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(steps):
            actions = torch.multinomial(self.mask.view(-1, a).float(), 1, generator=self.gen).view(b, n)
            self.mask = self.env.step(actions).mask
        if cuda:
            torch.cuda.synchronize()
        return steps * b * n / (time.perf_counter() - start)


class _OneByOne:
    """B separate ParallelEnvs stepped in turn with random valid moves from their masks."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.envs = [
            make_env(
                "target_localization",
                seed=args.seed + i,
                agents=args.agents,
                walls=args.walls,
                grid=args.grid,
            )
            for i in range(args.num_envs)
        ]
        self.rng = np.random.default_rng(args.seed)
        self.obs = [e.reset()[0] for e in self.envs]

    def rate(self, steps: int) -> float:
        agent_steps = 0
        start = time.perf_counter()
        for _ in range(steps):
            for i, env in enumerate(self.envs):
                acts = {}
                for agent in env.agents:
                    allowed = np.flatnonzero(self.obs[i][agent]["action_mask"])
                    acts[agent] = int(self.rng.choice(allowed))
                self.obs[i], *_ = env.step(acts)
                agent_steps += len(acts)
                if not env.agents:
                    self.obs[i] = env.reset()[0]
        return agent_steps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="medc-bench env", description=__doc__.split("\n\n")[0])
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=30)
    p.add_argument("--steps", type=int, default=200, help="timed batched steps per round")
    p.add_argument("--warmup", type=int, default=50, help="untimed batched steps first")
    p.add_argument(
        "--one-by-one-steps", type=int, default=3, help="timed steps of each ParallelEnv per round"
    )
    p.add_argument("--rounds", type=int, default=5, help="interleaved measurement rounds (medians reported)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(
        f"target localization A{args.agents}W{args.walls}, {args.grid}x{args.grid}, B={args.num_envs}, "
        f"device={args.device}, torch threads={args.threads}"
    )
    fast, fresh, one = _Batched(args, copy_obs=False), _Batched(args, copy_obs=True), _OneByOne(args)
    fast.rate(args.warmup), fresh.rate(max(1, args.warmup // 4)), one.rate(1)
    # Interleaved rounds, medians: on a shared machine every path sees the same load.
    rounds = {"fast": [], "fresh": [], "one": [], "ratio": []}
    for r in range(args.rounds):
        rounds["fast"].append(fast.rate(args.steps))
        rounds["fresh"].append(fresh.rate(max(1, args.steps // 4)))
        rounds["one"].append(one.rate(args.one_by_one_steps))
        rounds["ratio"].append(rounds["fast"][-1] / rounds["one"][-1])
        print(
            f"round {r + 1}: batched {rounds['fast'][-1]:,.0f}, batched copy_obs {rounds['fresh'][-1]:,.0f}, "
            f"one by one {rounds['one'][-1]:,.0f} agent-steps/s, ratio {rounds['ratio'][-1]:.1f}x"
        )
    batched, batched_copy, one_rate, ratio = (
        float(np.median(rounds[k])) for k in ("fast", "fresh", "one", "ratio")
    )
    print(f"median of {args.rounds} rounds:")
    print(f"batched core (in-place observation buffer): {batched:12,.0f} agent-steps/s")
    print(f"batched core (fresh observation tensors):   {batched_copy:12,.0f} agent-steps/s")
    print(f"one by one through the ParallelEnv API:     {one_rate:12,.0f} agent-steps/s")
    print(f"ratio batched / one by one:                 {ratio:12.1f}x")
    print(
        json.dumps(
            {
                "batched_agent_steps_per_s": round(batched),
                "batched_copy_obs_agent_steps_per_s": round(batched_copy),
                "one_by_one_agent_steps_per_s": round(one_rate),
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
