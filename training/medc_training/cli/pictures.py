"""``python -m medc_training.cli.pictures OUT_DIR``: Fig. 5-style pictures of each application.

Plays a few random valid moves in each environment, then writes ``<name>_area.png`` (the area)
and ``<name>_agent_0.png`` (agent 0's observation maps) under OUT_DIR, with the picture functions
of :mod:`medc_training.envs.render` (which the ParallelEnv itself draws with, so this command
lives apart from them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from medc_training.envs import ENV_NAMES, make_env
from medc_training.envs.render import save_frame_png, save_observation_png


def main(argv: list[str] | None = None) -> int:
    """Write the pictures (see the module docstring); prints each file written."""
    p = argparse.ArgumentParser(prog="python -m medc_training.cli.pictures",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("out_dir", type=Path)
    p.add_argument("--steps", type=int, default=25, help="random moves before the picture")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    for name in ENV_NAMES:
        env = make_env(name, seed=args.seed, render_mode="rgb_array")
        obs, _ = env.reset()
        for _ in range(args.steps):
            acts = {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}
            nxt, *_ = env.step(acts)
            if not env.agents:
                break
            obs = nxt
        area = save_frame_png(env.render(), args.out_dir / f"{name}_area.png")
        maps = save_observation_png(
            obs["agent_0"]["observation"], args.out_dir / f"{name}_agent_0.png", application=name,
            channel_names=env.core.observation_channels,
        )
        print(area)
        print(maps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
