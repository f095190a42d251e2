"""Generalized Advantage Estimation with the truncation / termination distinction.

A terminated episode (target found) has no future: the TD target is the reward alone.
A truncated episode (step limit reached) was cut short by the clock, not by the task, so
its TD target bootstraps from the critic's value of the episode's last observation
(``out.final_obs``). Either way the advantage does not flow across the episode boundary.
"""

from __future__ import annotations

import torch


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    terminated: torch.Tensor,
    truncated: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and returns for a rollout of T steps.

    Args:
        rewards: [T, ...] reward received after the action at step t.
        values: [T, ...] V(s_t).
        next_values: [T, ...] V(s_{t+1}) of the *same* episode: the next step's value while
            the episode runs on, V(final_obs) where it was truncated at t, anything where it
            terminated at t (ignored), and the bootstrap value after the last step.
        terminated, truncated: [T, ...] bool, the episode ended at step t.
        gamma, gae_lambda: discount and GAE λ.

    Returns:
        (advantages, returns), both shaped like ``values``; returns = advantages + values.
    """
    if not (rewards.shape == values.shape == next_values.shape == terminated.shape == truncated.shape):
        raise ValueError(
            "rewards, values, next_values, terminated and truncated must share one shape, got "
            f"{[tuple(t.shape) for t in (rewards, values, next_values, terminated, truncated)]}"
        )
    not_terminated = (~terminated.bool()).to(values.dtype)
    not_done = (~(terminated.bool() | truncated.bool())).to(values.dtype)
    advantages = torch.zeros_like(values)
    last = torch.zeros_like(values[0])
    for t in reversed(range(values.shape[0])):
        delta = rewards[t] + gamma * next_values[t] * not_terminated[t] - values[t]
        last = delta + gamma * gae_lambda * not_done[t] * last
        advantages[t] = last
    return advantages, advantages + values
