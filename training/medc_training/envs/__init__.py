"""The three multi-agent applications of the paper, as batched cores and PettingZoo envs.

``make_batched(name, num_envs=B, device=..., seed=..., **options)`` returns the batched core
(torch tensors, B environments stepped at once, auto-reset) that training uses;
``make_env(name, **options)`` returns a PettingZoo ``ParallelEnv`` over one environment.
See docs/environments.md.
"""

from __future__ import annotations

import inspect
from typing import Any

from medc_training.envs.core import BatchedEnv, StepOutput

ENV_NAMES: tuple[str, ...] = ("target_localization", "fleet_coordination", "maze_cleaning")
#: Target localization's worlds: ``grid`` (the project's layouts and sensing presets) and
#: ``radbench`` (the field benchmark's world on fresh episodes, medc_training.radbench.world).
WORLDS: tuple[str, ...] = ("grid", "radbench")

__all__ = [
    "ENV_NAMES", "WORLDS", "BatchedEnv", "StepOutput", "core_has_estimate", "core_options", "make_batched",
    "make_env",
]


def _core_class(name: str, world: str = "grid") -> type[BatchedEnv]:
    if name == "target_localization":
        if world not in WORLDS:
            raise ValueError(f"unknown world {str(world)[:40]!r} for target_localization; choose one of "
                             f"{', '.join(WORLDS)}")
        if world == "radbench":
            from medc_training.radbench.world import BenchWorld

            return BenchWorld
        from medc_training.envs.target_localization import TargetLocalization

        return TargetLocalization
    if world != "grid":
        raise ValueError(f"only target_localization has other worlds, not {name!r}")
    if name == "fleet_coordination":
        from medc_training.envs.fleet_coordination import FleetCoordination

        return FleetCoordination
    if name == "maze_cleaning":
        from medc_training.envs.maze_cleaning import MazeCleaning

        return MazeCleaning
    raise ValueError(f"unknown environment {name!r}; choose one of {', '.join(ENV_NAMES)}")


def core_options(name: str, world: str = "grid") -> tuple[str, ...]:
    """The keyword options application ``name``'s core takes (besides num_envs, device, seed) in
    ``world``; target localization's include ``world`` itself."""
    common = ("self", "num_envs", "device", "seed")
    signature = inspect.signature(_core_class(name, world).__init__)
    options = tuple(p for p in signature.parameters if p not in common)
    return (*options, "world") if name == "target_localization" else options


def core_has_estimate(name: str) -> bool:
    """Whether application ``name`` can show the team's source estimate (``+estimate`` views)."""
    return _core_class(name).HAS_ESTIMATE


def make_batched(
    name: str, num_envs: int = 1, device: str = "cpu", seed: int | None = None, **options: Any
) -> BatchedEnv:
    """The batched core of application ``name`` with ``num_envs`` environments on ``device``.

    Options per application (all keyword; unknown ones raise ValueError): see
    docs/environments.md, e.g. target_localization: agents, walls, grid, max_steps,
    reward_shaping, noise, world ("grid" or "radbench": the field benchmark's world).
    """
    world = options.pop("world", "grid")
    cls = _core_class(name, world)
    allowed = core_options(name, world)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        where = f"{name} in the {world} world" if world != "grid" else name
        raise ValueError(f"unknown option(s) {unknown} for {where}; allowed options: {', '.join(allowed)}")
    return cls(num_envs=num_envs, device=device, seed=seed, **options)


def make_env(name: str, render_mode: str | None = None, **options: Any):
    """A PettingZoo ``ParallelEnv`` over one environment of application ``name``.

    Options: those of :func:`make_batched` (except num_envs) plus ``render_mode``
    (None or "rgb_array").
    """
    from medc_training.envs.parallel import GridParallelEnv, check_render_mode

    check_render_mode(render_mode)
    if "num_envs" in options or "copy_obs" in options:
        raise ValueError("make_env always wraps one environment; use make_batched for num_envs/copy_obs")
    return GridParallelEnv(make_batched(name, num_envs=1, copy_obs=True, **options), render_mode)
