"""Evaluation: a policy (or uniformly random valid moves) plays a batched environment.

:func:`play_episodes` plays a *fixed* set of seeded episodes, each to its end (success or the
step limit), and returns them in episode order: episode ``i`` is the same for every policy
played from the same seed, and no episode is left out for being long. It is the product's one
evaluator: the training evaluation (:meth:`medc_training.ppo.Trainer.evaluate`), DAgger's
evaluations, the demo's expert reviews and random floor, and :mod:`medc_training.cli.play_bundle`,
which checks shipped bundles against a random team, e.g.::

    python -m medc_training.cli.play_bundle models/team/A3W2.safetensors --episodes 512

A run recorded with ``eval_episodes`` 0 was evaluated on the legacy window; the research harness
keeps that evaluator (``medc_lab.window``) and registers it here (:func:`register_evaluator`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .envs import make_batched
from .nets import masked_logits
from .stats import mean_ci

#: A policy: action logits [M, A] for observations [M, C, H, W] and their move masks [M, A]
#: (the loop masks the logits itself, so a policy may ignore the mask).
Policy = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: How sampled moves are drawn. Both draw from the same distribution, from a generator restarted
#: at the play seed, but give different draws: ``multinomial`` (torch.multinomial on the CPU) is
#: what DAgger's and the reproduction's random-play numbers were made with; ``gumbel`` (Gumbel-max
#: with uniform noise on the environment's device, no transfer to the host) is the training
#: evaluation's. Keeping both keeps every committed number reproducible.
SAMPLINGS: tuple[str, ...] = ("multinomial", "gumbel")


#: Evaluators kept outside the product, by name, as their package registers them.
_REGISTERED: dict[str, Callable[..., dict]] = {}


def register_evaluator(name: str, evaluate: Callable[..., dict]) -> None:
    """Make ``evaluate(env, policy, cfg, seed) -> summary`` the evaluator ``name``."""
    _REGISTERED[name] = evaluate


def registered_evaluator(name: str) -> Callable[..., dict]:
    """The evaluator ``name`` (RuntimeError when no package registered it)."""
    if name not in _REGISTERED:
        raise RuntimeError(f"no {name!r} evaluator here: a config with eval_episodes 0 is evaluated on "
                           "the legacy window, which the research harness keeps (import medc_lab.window, as "
                           "medc-reproduce does); evaluate new runs on fixed episodes (eval_episodes >= 1)")
    return _REGISTERED[name]


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
    """Played episodes: :func:`play_episodes`' in episode order (the legacy window's in the order
    they finished)."""

    lengths: tuple[int, ...]
    successes: tuple[bool, ...]
    returns: tuple[float, ...]

    def summary(self, default_length: float = 0.0) -> dict:
        """``episodes``, mean ``episode_length``, ``success_rate``, mean ``episode_return``."""
        return summarize_episodes(self.lengths, self.successes, self.returns, default_length)

    def ci95(self) -> dict[str, tuple[float, float]]:
        """(mean, half-width of the Student-t 95% CI over episodes) of ``episode_length`` and
        ``success_rate`` (medc_training.stats.mean_ci: half-width inf for one episode, nan for none)."""
        return {"episode_length": mean_ci([float(x) for x in self.lengths]),
                "success_rate": mean_ci([float(x) for x in self.successes])}


def net_policy(net: torch.nn.Module, device: torch.device | str | None = None) -> Policy:
    """The policy of an actor-critic network (its action logits), fed on ``device`` if given."""
    def logits(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return net(obs if device is None else obs.to(device))[0]

    return logits


def _check_positive(name: str, value) -> None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _check_sampling(sampling: str) -> None:
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")


def _choose(env, policy: Policy | None, obs: torch.Tensor, mask: torch.Tensor, greedy: bool, sampling: str,
            gen: torch.Generator) -> torch.Tensor:
    """int64 [B, N]: every agent's move, on ``env.device``: random valid moves without a policy,
    else its most probable valid move (``greedy``) or one drawn by ``sampling``."""
    B, N, A = env.num_envs, env.num_agents, env.num_actions
    device = gen.device
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
    return actions.view(B, N).to(env.device)


def _generator(env, seed: int, sampling: str) -> torch.Generator:
    """The sampling generator, restarted at ``seed`` (on the env's device for ``gumbel``)."""
    device = env.device if sampling == "gumbel" else torch.device("cpu")
    return torch.Generator(device=device).manual_seed(seed)


def round_seed(seed: int, round_index: int) -> int:
    """The reset seed of round ``round_index`` of :func:`play_episodes` from ``seed``: ``seed``
    itself for round 0 (the episodes the legacy window starts with), then a seed drawn from
    numpy's SeedSequence of (seed, round), in 0..2**63-1."""
    if round_index == 0:
        return seed
    return int(np.random.SeedSequence([seed, round_index]).generate_state(1, np.uint64)[0] >> 1)


@torch.no_grad()
def play_episodes(env, policy: Policy | None = None, *, episodes: int, seed: int = 12345, greedy: bool = True,
                  sampling: str = "multinomial") -> PlayResult:
    """Play exactly ``episodes`` fixed, seeded episodes, each to its end; in episode order.

    The ``B = env.num_envs`` environments play ``ceil(episodes / B)`` rounds. Round ``r`` resets
    ``env`` with :func:`round_seed` (seed, r) and lets each environment play its *first* episode
    to its end (success or ``env.max_steps``, so a round takes at most ``max_steps`` batched
    steps); the episodes that auto-reset after it are not counted. Episode ``i`` is environment
    ``i % B`` of round ``i // B``; its start comes from the reset seed alone, so it is the same
    episode for every policy played with the same ``env`` configuration, ``B`` and ``seed`` (as
    Stable-Baselines3's evaluate_policy divides its episodes over environments, but with every
    episode counted however long it lasts). The last round stops as soon as the episodes it
    needs have ended.

    ``policy`` None plays uniformly random valid moves (always sampled); otherwise ``greedy``
    takes the most probable valid move and ``greedy=False`` samples one (``sampling``: see
    :data:`SAMPLINGS`; one generator restarted at ``seed`` serves every round).
    """
    _check_positive("episodes", episodes)
    _check_sampling(sampling)
    limit = getattr(env, "max_steps", None)
    if not isinstance(limit, int) or limit < 1:
        raise ValueError(f"play_episodes needs an env with a positive integer max_steps, got {limit!r}")
    gen = _generator(env, seed, sampling)
    B = env.num_envs
    lengths: list[int] = []
    successes: list[bool] = []
    returns: list[float] = []
    for r in range(math.ceil(episodes / B)):
        wanted = min(B, episodes - r * B)  # the environments whose first episode is counted
        obs, mask = env.reset(seed=round_seed(seed, r))
        ret = torch.zeros(B, device=env.device)
        ended = torch.zeros(B, dtype=torch.bool, device=env.device)
        length = torch.zeros(B, dtype=torch.long, device=env.device)
        success = torch.zeros(B, dtype=torch.bool, device=env.device)
        for _ in range(limit):
            out = env.step(_choose(env, policy, obs, mask, greedy, sampling, gen))
            running = ~ended
            ret += torch.where(running, out.reward.to(env.device).float(), 0.0)
            now = (out.terminated | out.truncated).to(env.device) & running
            length = torch.where(now, out.episode_length.to(env.device), length)
            success = torch.where(now, out.success.to(env.device), success)
            ended |= now
            if bool(ended[:wanted].all()):
                break
            obs, mask = out.obs, out.mask
        else:
            raise RuntimeError(f"play_episodes: round {r} had episodes still running after max_steps "
                               f"= {limit} batched steps; the environment does not end its episodes there")
        lengths.extend(length[:wanted].tolist())
        successes.extend(success[:wanted].tolist())
        returns.extend(ret[:wanted].tolist())
    return PlayResult(tuple(lengths), tuple(successes), tuple(returns))


def evaluate_policy(env, policy=None, episodes: int = 256, greedy: bool = True, seed: int = 12345,
                    sampling: str = "multinomial") -> dict:
    """:func:`play_episodes` of ``episodes`` fixed episodes; its summary (mean length, success rate,
    mean return) with the 95% CI half-widths ``episode_length_ci95`` and ``success_rate_ci95``.

    ``policy`` is a :data:`Policy`, a PolicyBundle (anything with ``net`` and ``device``), or None
    for uniformly random valid moves. Greedy = most probable valid move; otherwise sampled.
    """
    if policy is not None and hasattr(policy, "net"):
        policy = net_policy(policy.net, policy.device)
    played = play_episodes(env, policy, episodes=episodes, greedy=greedy, seed=seed, sampling=sampling)
    ci = played.ci95()
    return {**played.summary(), "episode_length_ci95": ci["episode_length"][1],
            "success_rate_ci95": ci["success_rate"][1]}


def env_for_bundle(bundle, num_envs: int = 32, seed: int = 12345):
    """A batched environment matching the bundle manifest's application and attributes."""
    attrs = dict(bundle.manifest.get("environment", {}))
    if bundle.observation is not None:
        attrs["observation"] = bundle.observation
    return make_batched(bundle.manifest["application"], num_envs=num_envs, seed=seed, **attrs)
