"""The legacy window evaluator, kept to reproduce the numbers made with it.

The paper's protocol evaluated a run on a window of ``eval_steps`` batched test steps and kept
the episodes that finished inside it, which leans short. The committed reproduction's runs
(``eval_episodes`` 0, :data:`medc_training.config.LEGACY_EVAL`) and the random-play baselines
their gates compare with were measured so (:mod:`medc_lab.plan`, :mod:`medc_lab.report.reference_play`).
The product evaluates on fixed episodes only (:func:`medc_training.evaluate.play_episodes`);
importing this module (``import medc_lab`` does) registers :func:`evaluate_window` as the
evaluator of a config with ``eval_episodes`` 0.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from medc_training.envs import StepOutput
from medc_training.evaluate import (
    PlayResult,
    Policy,
    _check_positive,
    _check_sampling,
    _choose,
    _generator,
    register_evaluator,
)


@torch.no_grad()
def play(env, policy: Policy | None = None, *, episodes: int | None = None, steps: int | None = None,
         greedy: bool = True, seed: int = 12345, sampling: str = "multinomial",
         max_batched_steps: int = 100_000, on_step: Callable[[torch.Tensor, StepOutput], None] | None = None
         ) -> PlayResult:
    """Reset ``env`` from ``seed`` and let ``policy`` play every agent of every environment.

    Give exactly one of ``episodes`` (play until that many episodes finished, at most
    ``max_batched_steps`` batched steps, and keep the first ``episodes`` of them) or ``steps``
    (play exactly that many batched steps and keep every episode that finished): either way the
    episodes that finished first, which leans short. ``policy``, ``greedy`` and ``sampling`` as
    :func:`medc_training.evaluate.play_episodes` takes them; ``on_step(actions [B,N], out)``, if
    given, sees every step (e.g. to record a trace).
    """
    if (episodes is None) == (steps is None):
        raise ValueError("play needs exactly one of episodes= (finished episodes) or steps= (batched steps)")
    for name, value in (("episodes", episodes), ("steps", steps), ("max_batched_steps", max_batched_steps)):
        _check_positive(name, value)
    _check_sampling(sampling)
    gen = _generator(env, seed, sampling)
    obs, mask = env.reset(seed=seed)
    ret = torch.zeros(env.num_envs, device=env.device)
    lengths: list[int] = []
    successes: list[bool] = []
    returns: list[float] = []
    for _ in range(steps if steps is not None else max_batched_steps):
        actions = _choose(env, policy, obs, mask, greedy, sampling, gen)
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


def evaluate_window(env, policy: Policy, cfg, seed: int) -> dict:
    """A run's evaluation on the legacy window: ``cfg.eval_steps`` test steps (split over the
    environments), greedy or Gumbel-sampled as ``cfg.eval_greedy`` says, and the summary of the
    episodes that finished inside them (``cfg.max_steps`` as the length when none did)."""
    played = play(env, policy, steps=max(1, cfg.eval_steps // env.num_envs),
                  greedy=cfg.eval_greedy, seed=seed, sampling="gumbel")
    return played.summary(cfg.max_steps)


register_evaluator("window", evaluate_window)
