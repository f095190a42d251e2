"""Rollout storage for multi-agent PPO: [T, B, N] per-agent samples of a team rollout.

Each agent's transition is one sample for the shared actor-critic; the team reward and the
episode flags are per environment and are broadcast over the team's agents.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from .gae import compute_gae


class RolloutBuffer:
    """Fixed-size storage for ``steps`` batched steps of ``num_envs`` x ``num_agents``."""

    def __init__(self, steps: int, num_envs: int, num_agents: int, obs_shape: tuple, num_actions: int,
                 device: torch.device | str = "cpu") -> None:
        self.steps, self.num_envs, self.num_agents = steps, num_envs, num_agents
        T, B, N = steps, num_envs, num_agents
        d = torch.device(device)
        self.obs = torch.zeros((T, B, N, *obs_shape), dtype=torch.float32, device=d)
        self.masks = torch.zeros((T, B, N, num_actions), dtype=torch.bool, device=d)
        self.actions = torch.zeros((T, B, N), dtype=torch.long, device=d)
        self.logprobs = torch.zeros((T, B, N), device=d)
        self.values = torch.zeros((T, B, N), device=d)
        self.next_values = torch.zeros((T, B, N), device=d)
        self.rewards = torch.zeros((T, B), device=d)
        self.terminated = torch.zeros((T, B), dtype=torch.bool, device=d)
        self.truncated = torch.zeros((T, B), dtype=torch.bool, device=d)
        # IL-assisted RL: samples trained by behavioural cloning instead of PPO.
        self.bc = torch.zeros((T, B, N), dtype=torch.bool, device=d)
        self.advantages = torch.zeros((T, B, N), device=d)
        self.returns = torch.zeros((T, B, N), device=d)

    def compute_advantages(self, gamma: float, gae_lambda: float) -> None:
        """Fill advantages/returns (call after next_values is complete)."""
        shape = self.values.shape
        self.advantages, self.returns = compute_gae(
            self.rewards.unsqueeze(-1).expand(shape),
            self.values,
            self.next_values,
            self.terminated.unsqueeze(-1).expand(shape),
            self.truncated.unsqueeze(-1).expand(shape),
            gamma,
            gae_lambda,
        )

    def flat(self) -> dict[str, torch.Tensor]:
        """Every per-sample tensor flattened to [T*B*N, ...]."""
        n = self.steps * self.num_envs * self.num_agents
        return {
            "obs": self.obs.reshape(n, *self.obs.shape[3:]),
            "masks": self.masks.reshape(n, -1),
            "actions": self.actions.reshape(n),
            "logprobs": self.logprobs.reshape(n),
            "values": self.values.reshape(n),
            "advantages": self.advantages.reshape(n),
            "returns": self.returns.reshape(n),
            "bc": self.bc.reshape(n),
        }

    def minibatches(self, num_minibatches: int, generator: torch.Generator
                    ) -> Iterator[dict[str, torch.Tensor]]:
        """One epoch of shuffled minibatches (the last one takes the remainder)."""
        data = self.flat()
        n = data["actions"].shape[0]
        order = torch.randperm(n, generator=generator).to(data["actions"].device)
        for idx in order.chunk(num_minibatches):
            yield {k: v[idx] for k, v in data.items()}
