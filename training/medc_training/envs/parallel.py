"""PettingZoo ``ParallelEnv`` over one environment (a B=1 view of a batched core).

Agents are ``agent_0 .. agent_{N-1}``. Each agent's observation is a dict::

    {"observation": float32 [C,H,W] in [0, 1], "action_mask": int8 [A] (1 = move allowed)}

the convention PettingZoo's tests and samplers understand (``action_space(agent).sample(
mask=obs[agent]["action_mask"])``). A masked (invalid) move that is taken anyway leaves the
agent where it is. Rewards are the team reward, the same for every agent. When the episode
ends every agent is terminated (success) or truncated (``max_steps``) and leaves
``env.agents``; the observation returned then is the episode's last one, with an all-zero
action mask. ``infos[agent]`` then holds ``episode_length`` and ``success``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from medc_training.envs.core import BatchedEnv

RENDER_MODES = ("rgb_array",)


def check_render_mode(render_mode: str | None) -> None:
    """Raises ValueError unless ``render_mode`` is None or one of :data:`RENDER_MODES`."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")


class GridParallelEnv(ParallelEnv):
    """``make_env(name, **options)``: one environment of ``name`` as a PettingZoo ParallelEnv,
    over the batched core (B = 1, ``copy_obs=True``) that make_env builds for it."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": list(RENDER_MODES), "is_parallelizable": True}

    def __init__(self, core: BatchedEnv, render_mode: str | None = None) -> None:
        check_render_mode(render_mode)
        if core.num_envs != 1:
            raise ValueError(f"a ParallelEnv wraps one environment, got a core of {core.num_envs}")
        self.core = core
        self.render_mode = render_mode
        self.core.keep_pictures(render_mode is not None)
        self.metadata = {**GridParallelEnv.metadata, "name": f"medc_{core.name}_v0"}
        self.possible_agents = [f"agent_{i}" for i in range(self.core.num_agents)]
        self.agents: list[str] = []
        c, h, w = self.core.obs_shape
        # One space object per agent, built once: PettingZoo requires the same object on every call.
        self._observation_spaces = {
            a: spaces.Dict(
                {
                    "observation": spaces.Box(0.0, 1.0, (c, h, w), np.float32),
                    "action_mask": spaces.Box(0, 1, (self.core.num_actions,), np.int8),
                }
            )
            for a in self.possible_agents
        }
        self._action_spaces = {a: spaces.Discrete(self.core.num_actions) for a in self.possible_agents}
        self.observation_spaces = self._observation_spaces
        self.action_spaces = self._action_spaces
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None
        self._last_frame: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.core.name

    @property
    def attributes(self) -> dict[str, Any]:
        """The environment's descriptive features (same as the batched core's)."""
        return self.core.attributes

    def observation_space(self, agent: str) -> spaces.Dict:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._action_spaces[agent]

    def _obs_dict(self, obs: torch.Tensor, mask: torch.Tensor | None) -> dict[str, dict[str, np.ndarray]]:
        obs_np = obs[0].cpu().numpy()
        if mask is None:
            mask_np = np.zeros((self.core.num_agents, self.core.num_actions), dtype=np.int8)
        else:
            mask_np = mask[0].cpu().numpy().astype(np.int8)
        agents = self.possible_agents
        return {a: {"observation": obs_np[i], "action_mask": mask_np[i]} for i, a in enumerate(agents)}

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict]]:
        """Start an episode. Without ``seed``, after an episode ended, this continues with the
        episode the core already drew (so the wrapper follows the batched core step for step)."""
        if seed is None and self._pending is not None:
            obs, mask = self._pending
        else:
            obs, mask = self.core.reset(seed=seed)
        self._pending = None
        self._last_frame = None
        self.agents = list(self.possible_agents)
        return self._obs_dict(obs, mask), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("the episode is over (env.agents is empty): call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"every live agent needs an action; missing {missing}")
        try:
            acts = [int(actions[a]) for a in self.possible_agents]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"actions must be integers in 0..{self.core.num_actions - 1}") from exc
        self._last_frame = None
        # The core resets itself when the episode ends: keep what the last picture needs.
        extras = self.core.render_extras(0) if self.render_mode == "rgb_array" else None
        out = self.core.step(torch.tensor([acts], dtype=torch.long, device=self.core.device))
        reward = float(out.reward[0])
        term, trunc = bool(out.terminated[0]), bool(out.truncated[0])
        agents = list(self.agents)
        rewards = dict.fromkeys(agents, reward)
        terminations = dict.fromkeys(agents, term)
        truncations = dict.fromkeys(agents, trunc)
        if term or trunc:
            obs = self._obs_dict(out.final_obs, None)
            info = {"episode_length": int(out.episode_length[0]), "success": bool(out.success[0])}
            infos = {a: dict(info) for a in agents}
            self._pending = (out.obs, out.mask)
            if self.render_mode == "rgb_array":
                from medc_training.envs.render import render_frame

                picture = self.core.final_picture_maps(0, out.final_obs)
                self._last_frame = render_frame(self.core.name, picture, extras)
            self.agents = []
        else:
            obs = self._obs_dict(out.obs, out.mask)
            infos = {a: {} for a in agents}
        return obs, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """``rgb_array``: uint8 [H_px, W_px, 3] picture of the area (paper Fig. 5a style)."""
        if self.render_mode is None:
            return None
        if self._last_frame is not None:
            return self._last_frame
        from medc_training.envs.render import render_frame

        return render_frame(self.core.name, self.core.picture_maps(0), self.core.render_extras(0))

    def close(self) -> None:
        self._pending = None

    def state(self) -> np.ndarray:
        """Global state: the stacked observation maps of all agents, float32 [N,C,H,W]."""
        return self.core.current_obs(0).cpu().numpy()
