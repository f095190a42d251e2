"""``medc-controllers``: the classical search controllers (and random moves) played on a target
localization scenario, the first episode of every environment to its end; one JSON line each."""

from __future__ import annotations

import argparse
import json

from ..controllers import CONTROLLERS, controller_policy, first_episodes
from ..envs import make_batched
from ..envs.names import TARGET_LOCALIZATION


def main(argv: list[str] | None = None) -> int:
    """``medc-controllers``: evaluate classical controllers (and random moves) on a target
    localization scenario; one JSON line per controller."""
    p = argparse.ArgumentParser(
        description="Evaluate classical search controllers on target localization: the first episode "
                    "of every environment, played to its end; one JSON line each.")
    p.add_argument("controllers", nargs="*", default=list(CONTROLLERS),
                   help=f"any of {', '.join(CONTROLLERS)}, random (default: every controller)")
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=20)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--sensing", default="realistic")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    for name in args.controllers:
        if name != "random" and name not in CONTROLLERS:
            p.error(f"unknown controller {name!r}; choose from {', '.join(CONTROLLERS)}, random")
    for name in args.controllers:
        env = make_batched(TARGET_LOCALIZATION, num_envs=args.num_envs, device=args.device, seed=args.seed,
                           agents=args.agents, walls=args.walls, grid=args.grid, max_steps=args.max_steps,
                           sensing=args.sensing, posterior=True)
        policy = None if name == "random" else controller_policy(name, env)
        result = first_episodes(env, policy, seed=args.seed)
        print(json.dumps({"controller": name, **env.attributes, "sensing": env.sensing.name,
                          "num_envs": args.num_envs, "seed": args.seed, **result}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
