"""``python -m medc_training.cli.play_bundle BUNDLE``: a policy bundle played greedily and sampled
against a random team on the same fixed episodes, each to its end; one JSON line."""

from __future__ import annotations

import argparse
import json

from ..bundle import load_bundle
from ..evaluate import env_for_bundle, evaluate_policy


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_training.cli.play_bundle",
                                description="Evaluate a policy bundle against a random team on the same "
                                            "fixed episodes, each played to its end (play_episodes).")
    p.add_argument("bundle")
    p.add_argument("--episodes", type=int, default=256, help="episodes (default 256)")
    p.add_argument("--envs", type=int, default=32,
                   help="environments the episodes are split over (default 32)")
    p.add_argument("--seed", type=int, default=12345)
    args = p.parse_args(argv)
    bundle = load_bundle(args.bundle)

    def run(policy, greedy):
        env = env_for_bundle(bundle, num_envs=args.envs, seed=args.seed)
        return evaluate_policy(env, policy, args.episodes, greedy, args.seed)

    result = {"greedy": run(bundle, True), "sampled": run(bundle, False), "random": run(None, False)}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
