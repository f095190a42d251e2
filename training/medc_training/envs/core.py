"""What every batched environment core shares: the step result, seeding, option checks.

A batched core steps ``num_envs`` independent copies of one application at once, with
torch tensor operations only (no numpy and no Python loop over the batch in ``step``), so
the same code runs on a CUDA device. Finished environments reset automatically; the last
observation of the finished episode is returned in :attr:`StepOutput.final_obs` so that
PPO can bootstrap truncated episodes.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from typing import Any

import torch


@dataclass
class StepOutput:
    """Result of :meth:`BatchedEnv.step` for ``B`` environments of ``N`` agents.

    obs:            float32 [B,N,C,H,W] next observation; already the new episode's first
                    observation where the environment finished (auto-reset).
    mask:           bool [B,N,A] allowed actions for ``obs`` (True = allowed).
    reward:         float32 [B] team reward, shared by the team's agents.
    terminated:     bool [B] the task was completed (success).
    truncated:      bool [B] max_steps reached without success (PPO bootstraps these).
    final_obs:      float32 [B,N,C,H,W] last observation of the finished episode, valid only
                    where ``terminated | truncated`` (it may be the same tensor as ``obs``
                    when no environment finished).

    With ``copy_obs=False`` (an option of the cores) ``obs`` and ``final_obs`` are buffers
    the env reuses: the next ``step``/``reset`` overwrites them, so copy what you keep.
    episode_length: int64 [B] steps taken in the finished episode (valid where done).
    success:        bool [B] the finished episode succeeded (valid where done).
    """

    obs: torch.Tensor
    mask: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    final_obs: torch.Tensor
    episode_length: torch.Tensor
    success: torch.Tensor

    @property
    def done(self) -> torch.Tensor:
        """bool [B]: the episode ended this step (terminated or truncated)."""
        return self.terminated | self.truncated


class BatchedEnv:
    """Interface shared by the three batched cores (see the concrete classes).

    Attributes: ``num_envs``, ``num_agents``, ``num_actions``, ``obs_shape`` (C, H, W),
    ``device``, ``name``, ``attributes`` (dict of the environment's descriptive features).
    """

    name: str = ""
    num_envs: int
    num_agents: int
    num_actions: int
    obs_shape: tuple[int, int, int]
    device: torch.device
    max_steps: int

    def __init__(self, num_envs: int, device: str | torch.device, seed: int | None) -> None:
        self.num_envs = check_int("num_envs", num_envs, 1, 1_000_000)
        try:
            self.device = torch.device(device)
        except (RuntimeError, TypeError) as exc:
            raise ValueError(
                f"device must be a torch device such as 'cpu' or 'cuda', got {device!r}"
            ) from exc
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {device!r} requested but CUDA is not available here; use 'cpu'")
        self.generator = torch.Generator(device=self.device)
        self._seed(seed)

    def _seed(self, seed: int | None) -> None:
        if seed is None:
            seed = secrets.randbits(63)
        self.generator.manual_seed(check_int("seed", seed, 0, 2**63 - 1))

    @property
    def attributes(self) -> dict[str, Any]:
        raise NotImplementedError

    def reset(self, seed: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Start a new episode in every environment; returns (obs [B,N,C,H,W], mask [B,N,A])."""
        raise NotImplementedError

    def step(self, actions: torch.Tensor) -> StepOutput:
        """Apply one action per agent (int64 [B,N]); finished environments auto-reset."""
        raise NotImplementedError

    def oracle_action_scores(self) -> torch.Tensor:
        """float32 [B,N,A] scripted expert's scores for the current state (-inf = invalid)."""
        raise NotImplementedError

    def current_obs(self, index: int) -> torch.Tensor:
        """float32 [N,C,H,W]: the current observations of environment ``index`` (a copy)."""
        return self._obs[index].clone()

    def render_extras(self, index: int) -> dict[str, Any]:
        """What a picture of environment ``index`` needs beyond the observation maps."""
        return {}

    def _check_actions(self, actions: torch.Tensor) -> torch.Tensor:
        actions = torch.as_tensor(actions, device=self.device)
        if actions.shape != (self.num_envs, self.num_agents):
            raise ValueError(
                f"actions must have shape (num_envs, num_agents) = {(self.num_envs, self.num_agents)}, "
                f"got {tuple(actions.shape)}"
            )
        if actions.dtype.is_floating_point or actions.dtype == torch.bool:
            raise ValueError(f"actions must be an integer tensor, got {actions.dtype}")
        lo, hi = torch.aminmax(actions)
        if int(lo) < 0 or int(hi) >= self.num_actions:
            raise ValueError(
                f"actions must be in 0..{self.num_actions - 1}, got values in {int(lo)}..{int(hi)}"
            )
        return actions.long()


def check_int(name: str, value: Any, lo: int, hi: int) -> int:
    """Return ``value`` as an int if ``lo <= value <= hi``; otherwise raise ValueError saying so."""
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    value = int(value.__index__())
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value}")
    return value


def check_bool(name: str, value: Any) -> bool:
    """Return ``value`` if it is a bool; otherwise raise ValueError."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return value
