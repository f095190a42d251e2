"""The one play loop: a policy (or uniformly random valid moves) plays a batched environment.

Every evaluation in the project plays through :func:`play`: the training evaluation
(:meth:`medc_training.ppo.Trainer.evaluate`), DAgger's evaluations, the reproduction's random
baseline, the demo's expert reviews and random floor, and this module's command line, which
checks shipped bundles against a random team, e.g.::

    python -m medc_training.evaluate models/team/A3W2.safetensors --episodes 256
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .envs import StepOutput, make_batched
from .nets import masked_logits

#: A policy: action logits [M, A] for observations [M, C, H, W] and their move masks [M, A]
#: (the loop masks the logits itself, so a policy may ignore the mask).
Policy = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: How sampled moves are drawn. Both draw from the same distribution, from a generator restarted
#: at the play seed, but give different draws: ``multinomial`` (torch.multinomial on the CPU) is
#: what DAgger's and the reproduction's random-play numbers were made with; ``gumbel`` (Gumbel-max
#: with uniform noise on the environment's device, no transfer to the host) is the training
#: evaluation's. Keeping both keeps every committed number reproducible.
SAMPLINGS: tuple[str, ...] = ("multinomial", "gumbel")


def summarize_episodes(lengths: Sequence[float], successes: Sequence[float], returns: Sequence[float],
                       default_length: float = 0.0) -> dict:
    """Mean episode length, success rate and return of finished episodes (``default_length`` and
    zeros when none finished)."""
    n = len(lengths)
    return {
        "episodes": n,
        "episode_length": float(np.mean(lengths)) if n else float(default_length),
        "success_rate": float(np.mean(successes)) if n else 0.0,
        "episode_return": float(np.mean(returns)) if n else 0.0,
    }


@dataclass(frozen=True)
class PlayResult:
    """The finished episodes of one :func:`play`, in the order they finished."""

    lengths: tuple[int, ...]
    successes: tuple[bool, ...]
    returns: tuple[float, ...]

    def summary(self, default_length: float = 0.0) -> dict:
        """``episodes``, mean ``episode_length``, ``success_rate``, mean ``episode_return``."""
        return summarize_episodes(self.lengths, self.successes, self.returns, default_length)


def net_policy(net: torch.nn.Module, device: torch.device | str | None = None) -> Policy:
    """The policy of an actor-critic network (its action logits), fed on ``device`` if given."""
    def logits(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return net(obs if device is None else obs.to(device))[0]

    return logits


@torch.no_grad()
def play(env, policy: Policy | None = None, *, episodes: int | None = None, steps: int | None = None,
         greedy: bool = True, seed: int = 12345, sampling: str = "multinomial",
         max_batched_steps: int = 100_000, on_step: Callable[[torch.Tensor, StepOutput], None] | None = None
         ) -> PlayResult:
    """Reset ``env`` from ``seed`` and let ``policy`` play every agent of every environment.

    Give exactly one of ``episodes`` (play until that many episodes finished, at most
    ``max_batched_steps`` batched steps, and keep the first ``episodes`` of them) or ``steps``
    (play exactly that many batched steps and keep every episode that finished). ``policy`` None
    plays uniformly random valid moves (always sampled); otherwise ``greedy`` takes the most
    probable valid move and ``greedy=False`` samples one (``sampling``: see :data:`SAMPLINGS`).
    ``on_step(actions [B,N], out)``, if given, sees every step (e.g. to record a trace).
    """
    if (episodes is None) == (steps is None):
        raise ValueError("play needs exactly one of episodes= (finished episodes) or steps= (batched steps)")
    for name, value in (("episodes", episodes), ("steps", steps), ("max_batched_steps", max_batched_steps)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    device = env.device if sampling == "gumbel" else torch.device("cpu")
    gen = torch.Generator(device=device).manual_seed(seed)
    obs, mask = env.reset(seed=seed)
    B, N, A = env.num_envs, env.num_agents, env.num_actions
    ret = torch.zeros(B, device=env.device)
    lengths: list[int] = []
    successes: list[bool] = []
    returns: list[float] = []
    for _ in range(steps if steps is not None else max_batched_steps):
        flat_mask = mask.reshape(B * N, A)
        if policy is None:
            logits = torch.zeros(B * N, A, device=device)
        else:
            logits = policy(obs.reshape(B * N, *env.obs_shape), flat_mask).to(device)
        logits = masked_logits(logits, flat_mask.to(device))
        if greedy and policy is not None:
            actions = logits.argmax(-1)
        elif sampling == "gumbel":
            uniform = torch.rand(logits.shape, generator=gen, device=device)
            actions = (logits - torch.log(-torch.log(uniform.clamp_min(1e-20)))).argmax(-1)
        else:
            actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=gen).squeeze(-1)
        actions = actions.view(B, N).to(env.device)
        out = env.step(actions)
        if on_step is not None:
            on_step(actions, out)
        ret += out.reward.to(env.device).float()
        done = out.terminated | out.truncated
        if done.any():
            idx = done.nonzero(as_tuple=True)[0]
            lengths.extend(out.episode_length[idx].tolist())
            successes.extend(out.success[idx].tolist())
            returns.extend(ret[idx].tolist())
            ret[idx] = 0.0
        obs, mask = out.obs, out.mask
        if episodes is not None and len(lengths) >= episodes:
            break
    keep = len(lengths) if episodes is None else episodes
    return PlayResult(tuple(lengths[:keep]), tuple(successes[:keep]), tuple(returns[:keep]))


def evaluate_policy(env, policy=None, episodes: int = 256, greedy: bool = True, seed: int = 12345,
                    max_batched_steps: int = 100_000) -> dict:
    """:func:`play` until ``episodes`` episodes finished; its summary (mean length, success rate,
    mean return).

    ``policy`` is a :data:`Policy`, a PolicyBundle (anything with ``net`` and ``device``), or None
    for uniformly random valid moves. Greedy = most probable valid move; otherwise sampled.
    """
    if policy is not None and hasattr(policy, "net"):
        policy = net_policy(policy.net, policy.device)
    return play(env, policy, episodes=episodes, greedy=greedy, seed=seed,
                max_batched_steps=max_batched_steps).summary()


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
