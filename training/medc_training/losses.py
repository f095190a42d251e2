"""The PPO clipped objective and the behavioural-cloning loss, per minibatch.

Both operate on per-sample tensors so that IL-assisted RL can train some samples (those
from expert episodes) with BC and the rest with PPO in the same minibatch.
"""

from __future__ import annotations

import torch


def ppo_policy_loss(new_logprob: torch.Tensor, old_logprob: torch.Tensor, advantages: torch.Tensor,
                    clip: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample clipped surrogate loss (to minimise) and the log-ratio.

    L = -min(r A, clip(r, 1-ε, 1+ε) A), r = π_θ(a|s) / π_θold(a|s).
    """
    log_ratio = new_logprob - old_logprob
    ratio = log_ratio.exp()
    unclipped = ratio * advantages
    clipped = ratio.clamp(1.0 - clip, 1.0 + clip) * advantages
    return -torch.min(unclipped, clipped), log_ratio


def value_loss(new_value: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Per-sample squared error of the critic against the GAE returns (×0.5)."""
    return 0.5 * (new_value - returns) ** 2


def bc_loss(masked_logits: torch.Tensor, expert_actions: torch.Tensor) -> torch.Tensor:
    """Per-sample behavioural-cloning loss: -log π_θ(a_expert | s) under the masked policy."""
    logp = torch.log_softmax(masked_logits, dim=-1)
    return -logp.gather(-1, expert_actions.long().unsqueeze(-1)).squeeze(-1)


def masked_mean(values: torch.Tensor, select: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` over ``select`` (0 when nothing is selected, keeping the graph)."""
    w = select.to(values.dtype)
    return (values * w).sum() / w.sum().clamp_min(1.0)


def approx_kl(log_ratio: torch.Tensor) -> torch.Tensor:
    """The low-variance KL estimator (r - 1) - log r, averaged."""
    return ((log_ratio.exp() - 1) - log_ratio).mean()
