"""The three multi-agent applications of the paper, as batched cores and PettingZoo envs.

``make_batched(name, num_envs=B, device=..., seed=..., **options)`` returns the batched core
(torch tensors, B environments stepped at once, auto-reset) that training uses;
``make_env(name, **options)`` returns a PettingZoo ``ParallelEnv`` over one environment.
See docs/environments.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from medc_training.envs.names import DEFAULT_APPLICATION, ENV_NAMES

if TYPE_CHECKING:
    from medc_training.envs.core import BatchedEnv

#: Target localization's worlds: ``grid`` (the project's layouts and sensing presets) and
#: ``radbench`` (the field benchmark's world on fresh episodes, medc_training.radbench.world).
WORLDS: tuple[str, ...] = ("grid", "radbench")

__all__ = [
    "APPLICATIONS", "DEFAULT_APPLICATION", "ENV_NAMES", "WORLDS", "Application", "BatchedEnv", "StepOutput",
    "application", "core_options", "make_batched", "make_env", "register", "unregister",
]
#: Names imported when first asked (they need torch): name -> its module.
_LAZY = {"BatchedEnv": "core", "StepOutput": "core", "Application": "descriptor",
         "application": "descriptor", "register": "descriptor", "unregister": "descriptor"}


def __getattr__(name: str) -> Any:
    if name == "APPLICATIONS":
        from medc_training.envs.descriptor import applications

        return applications()
    if name in _LAZY:
        return getattr(importlib.import_module(f"medc_training.envs.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def core_options(name: str, world: str = "grid") -> tuple[str, ...]:
    """The keyword options application ``name``'s core takes (besides num_envs, device, seed) in
    ``world`` (:meth:`Application.options`)."""
    from medc_training.envs.descriptor import application

    return application(name).options(world)


def make_batched(
    name: str, num_envs: int = 1, device: str = "cpu", seed: int | None = None, **options: Any
) -> BatchedEnv:
    """The batched core of application ``name`` with ``num_envs`` environments on ``device``.

    Options per application (all keyword; unknown ones raise ValueError): see
    docs/environments.md, e.g. target_localization: agents, walls, grid, max_steps,
    reward_shaping, noise, world ("grid" or "radbench": the field benchmark's world).
    """
    from medc_training.envs.descriptor import application

    world = options.pop("world", "grid")
    app = application(name)
    cls = app.core_class(world)
    allowed = app.options(world)
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
