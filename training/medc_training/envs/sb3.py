"""The batched environments for Stable-Baselines3, with the action mask (sb3-contrib's
``MaskablePPO`` convention).

:class:`MaskableVecEnv` is a vectorised environment in SB3's ``VecEnv`` interface whose slots are
the (environment, agent) pairs of a batched core: ``num_envs = B * N``, slot ``k`` is agent
``k % N`` of environment ``k // N``; every slot sees its agent's observation (float32
[C,H,W] in [0, 1]) and gets the team reward (parameter sharing, as this project's learner
trains). ``action_masks()`` returns bool [B*N, A], True = allowed, which ``MaskablePPO`` reads
through ``env_method("action_masks")``; a masked move taken anyway leaves the agent where it is.
When an environment's episode ends, its N slots are ``done`` together, their observation is
already the next episode's, and ``infos[k]`` holds ``terminal_observation``,
``TimeLimit.truncated``, ``is_success`` and ``episode`` (``r``: the episode's team return,
``l``: its length), what SB3's ``Monitor`` would add.

When ``stable_baselines3`` is installed the class is a real ``VecEnv`` subclass (so
``MaskablePPO("MlpPolicy", MaskableVecEnv(...))`` takes it as it is); without it, the same
class stands alone with the same methods. Neither SB3 nor sb3-contrib is a dependency here::

    from sb3_contrib import MaskablePPO
    from medc_training.envs.sb3 import MaskableVecEnv

    env = MaskableVecEnv("target_localization", num_envs=8, seed=0, agents=3, walls=2, grid=13, max_steps=50)
    MaskablePPO("MlpPolicy", env, n_steps=128).learn(100_000)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from . import make_batched


def _vec_env_base() -> type:
    try:
        from stable_baselines3.common.vec_env import VecEnv
    except ImportError:
        return object
    return VecEnv


class MaskableVecEnv(_vec_env_base()):
    """``num_envs`` environments of application ``name`` as B*N SB3 slots (module docstring).

    ``options``: those of :func:`medc_training.envs.make_batched` (agents, walls, grid, ...).
    """

    def __init__(self, name: str = "target_localization", num_envs: int = 1, seed: int | None = 0,
                 device: str = "cpu", **options: Any) -> None:
        self.core = make_batched(name, num_envs=num_envs, device=device, seed=seed, copy_obs=True, **options)
        self.B, self.N, self.A = self.core.num_envs, self.core.num_agents, self.core.num_actions
        c, h, w = self.core.obs_shape
        observation_space = spaces.Box(0.0, 1.0, (c, h, w), np.float32)
        action_space = spaces.Discrete(self.A)
        self.render_mode = None
        self._seed = seed
        self._actions: np.ndarray | None = None
        self._mask: torch.Tensor | None = None
        self._returns = np.zeros(self.B, dtype=np.float64)
        if _vec_env_base() is object:
            self.num_envs = self.B * self.N
            self.observation_space, self.action_space = observation_space, action_space
        else:
            super().__init__(self.B * self.N, observation_space, action_space)

    # -- the VecEnv interface ---------------------------------------------------------------
    def _flat(self, obs: torch.Tensor) -> np.ndarray:
        return obs.reshape(self.B * self.N, *self.core.obs_shape).cpu().numpy().astype(np.float32, copy=False)

    def reset(self) -> np.ndarray:
        """Start every environment's episode; the observations, float32 [B*N, C, H, W]."""
        obs, mask = self.core.reset(seed=self._seed)
        self._seed = None  # seeded once; later resets continue the core's stream
        self._mask = mask
        self._returns[:] = 0.0
        return self._flat(obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(self.B * self.N)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async(actions)")
        if self._mask is None:
            raise RuntimeError("call reset() before step()")
        acts = torch.as_tensor(self._actions.astype(np.int64), device=self.core.device)
        acts = acts.reshape(self.B, self.N)
        self._actions = None
        out = self.core.step(acts)
        reward = out.reward.cpu().numpy().astype(np.float32)
        self._returns += reward
        ended = (out.terminated | out.truncated).cpu().numpy()
        infos: list[dict] = [{} for _ in range(self.B * self.N)]
        if ended.any():
            final = out.final_obs.cpu().numpy()
            term, trunc = out.terminated.cpu().numpy(), out.truncated.cpu().numpy()
            lengths, success = out.episode_length.cpu().numpy(), out.success.cpu().numpy()
            for b in np.flatnonzero(ended):
                episode = {"r": float(self._returns[b]), "l": int(lengths[b])}
                for i in range(self.N):
                    infos[b * self.N + i] = {
                        "terminal_observation": final[b, i].astype(np.float32),
                        "TimeLimit.truncated": bool(trunc[b] and not term[b]),
                        "is_success": bool(success[b]),
                        "episode": dict(episode),
                    }
                self._returns[b] = 0.0
        self._mask = out.mask
        return (self._flat(out.obs), np.repeat(reward, self.N), np.repeat(ended, self.N), infos)

    def step(self, actions: np.ndarray):
        """``step_async`` then ``step_wait``."""
        self.step_async(actions)
        return self.step_wait()

    def action_masks(self) -> np.ndarray:
        """bool [B*N, A]: the moves each slot may take now (sb3-contrib's ``action_masks()``)."""
        if self._mask is None:
            raise RuntimeError("call reset() before action_masks()")
        return self._mask.reshape(self.B * self.N, self.A).cpu().numpy().astype(bool)

    def _indices(self, indices: int | Sequence[int] | None) -> list[int]:
        if indices is None:
            return list(range(self.B * self.N))
        return [int(indices)] if isinstance(indices, int | np.integer) else [int(i) for i in indices]

    def env_method(self, method_name: str, *args: Any, indices=None, **kwargs: Any) -> list:
        """Per slot: ``action_masks`` gives each slot's mask (what MaskablePPO stacks)."""
        idx = self._indices(indices)
        if method_name == "action_masks":
            masks = self.action_masks()
            return [masks[i] for i in idx]
        raise AttributeError(f"MaskableVecEnv slots have no method {method_name!r} (only action_masks)")

    def get_attr(self, attr_name: str, indices=None) -> list:
        """``[getattr(self, attr_name)] * len(indices)`` (AttributeError when there is none)."""
        value = getattr(self, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
        """No gymnasium wrappers: the episode statistics come in ``infos`` (see the docstring)."""
        return [False for _ in self._indices(indices)]

    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seed the next ``reset()``."""
        self._seed = seed
        return [seed for _ in range(self.B * self.N)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.B * self.N)]

    def close(self) -> None:
        self._mask = None
