"""Evaluate a policy bundle (or a uniformly random policy) on its environment.

Used to check shipped bundles against a random team, e.g.::

    python -m medc_training.evaluate models/team/A3W2.safetensors --episodes 256
"""

from __future__ import annotations

import argparse
import json

import torch

from .envs import make_batched
from .nets import masked_logits


def evaluate_policy(env, policy=None, episodes: int = 256, greedy: bool = True, seed: int = 12345,
                    max_batched_steps: int = 100_000) -> dict:
    """Play until ``episodes`` episodes finished; mean length and success rate.

    ``policy`` is a PolicyBundle (or anything with ``net``), or None for uniformly random
    valid moves. Greedy = most probable valid move; otherwise sampled.
    """
    gen = torch.Generator().manual_seed(seed)
    obs, mask = env.reset(seed=seed)
    B, N, A = env.num_envs, env.num_agents, env.num_actions
    lengths: list[int] = []
    successes: list[bool] = []
    for _ in range(max_batched_steps):
        flat_mask = mask.reshape(B * N, A)
        if policy is None:
            logits = torch.zeros(B * N, A)
        else:
            with torch.no_grad():
                logits, _ = policy.net(obs.reshape(B * N, *env.obs_shape).to(policy.device))
            logits = logits.cpu()
        logits = masked_logits(logits, flat_mask.cpu())
        if greedy and policy is not None:
            actions = logits.argmax(-1)
        else:
            actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=gen).squeeze(-1)
        out = env.step(actions.view(B, N).to(env.device))
        done = (out.terminated | out.truncated).cpu()
        lengths.extend(out.episode_length.cpu()[done].tolist())
        successes.extend(out.success.cpu()[done].tolist())
        obs, mask = out.obs, out.mask
        if len(lengths) >= episodes:
            break
    lengths, successes = lengths[:episodes], successes[:episodes]
    return {"episodes": len(lengths), "episode_length": sum(lengths) / max(1, len(lengths)),
            "success_rate": sum(successes) / max(1, len(successes))}


def env_for_bundle(bundle, num_envs: int = 32, seed: int = 12345):
    """A batched environment matching the bundle manifest's application and attributes."""
    attrs = dict(bundle.manifest.get("environment", {}))
    if bundle.observation is not None:
        attrs["observation"] = bundle.observation
    return make_batched(bundle.manifest["application"], num_envs=num_envs, seed=seed, **attrs)


def main(argv: list[str] | None = None) -> int:
    from .bundle import load_bundle

    p = argparse.ArgumentParser(description="Evaluate a policy bundle against a random team.")
    p.add_argument("bundle")
    p.add_argument("--episodes", type=int, default=256)
    p.add_argument("--seed", type=int, default=12345)
    args = p.parse_args(argv)
    bundle = load_bundle(args.bundle)
    def run(policy, greedy):
        env = env_for_bundle(bundle, seed=args.seed)
        return evaluate_policy(env, policy, args.episodes, greedy, args.seed)

    result = {"greedy": run(bundle, True), "sampled": run(bundle, False), "random": run(None, False)}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
