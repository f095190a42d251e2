"""What the rest of the project knows of an application: its :class:`Application` descriptor.

Each application module declares one next to its core and registers it (:func:`register`);
:func:`applications` and :func:`application` import the paper's three modules first, so the
registry always holds them. Code outside ``envs/`` asks a descriptor (a capability, the default
observation, the option schema, the manifest fields) instead of testing an application's name.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from medc_training.envs.names import ENV_NAMES
from medc_training.envs.observation import OBSERVATION_FORMS, ObservationSpec, parse_observation

__all__ = ["Application", "application", "applications", "register", "unregister"]

#: The applications this code knows, by name: the paper's (ENV_NAMES order), then any registered.
_REGISTRY: dict[str, Application] = {}
_loaded = False
_COMMON = ("self", "num_envs", "device", "seed")


@dataclass(frozen=True)
class Application:
    """One application: its core, observations, capabilities, option schema and manifest fields."""

    name: str
    core: type
    """The batched core of the ``grid`` world (a :class:`~medc_training.envs.core.BatchedEnv`)."""
    default_observation: str
    """The observation a core takes when none is given."""
    channels: Callable[[ObservationSpec], tuple[str, ...]]
    """The channel names of an accepted view, in order."""
    has_estimate: bool = False
    """It can show the team's source estimate: it accepts the ``+estimate`` and ``+posterior`` views."""
    sensing_presets: tuple[str, ...] = ()
    """The sensing presets it takes (``sensing`` option), the default first; () when none."""
    controllers: bool = False
    """The classical controllers (medc_training.controllers) can play it."""
    other_worlds: tuple[tuple[str, str], ...] = ()
    """Worlds besides ``grid``: (world, "module:Class" of its core, imported when asked)."""
    observation_in_config: bool = False
    """The run config's ``observation`` field always reaches the core (else only when it differs
    from the observation the scales name, the default application's default, or through
    ``env_options``)."""
    action_names: tuple[str, ...] = ()
    """The name of each action, as bundle manifests list them (none: 'action_0', ...)."""
    manifest_names_view: bool = False
    """Its bundle manifests always name their view, and the view fixes the channel names; a
    manifest without a name takes 'maps'. Otherwise the name is recorded only for a view other
    than 'maps' and the channel names are the bundle's own."""

    @property
    def worlds(self) -> tuple[str, ...]:
        return ("grid", *(world for world, _ in self.other_worlds))

    @property
    def default_sensing(self) -> str | None:
        return self.sensing_presets[0] if self.sensing_presets else None

    def core_class(self, world: str = "grid") -> type:
        """The core of ``world`` (ValueError for a world it does not have)."""
        if world == "grid":
            return self.core
        for name, where in self.other_worlds:
            if name == world:
                module, _, cls = where.partition(":")
                return getattr(importlib.import_module(module), cls)
        if not self.other_worlds:
            raise ValueError(f"{self.name} has only the grid world, not {str(world)[:40]!r}")
        raise ValueError(f"unknown world {str(world)[:40]!r} for {self.name}; choose one of "
                         f"{', '.join(self.worlds)}")

    def options(self, world: str = "grid") -> tuple[str, ...]:
        """The keyword options its core takes in ``world`` (besides num_envs, device, seed);
        ``world`` among them when it has other worlds."""
        signature = inspect.signature(self.core_class(world).__init__)
        options = tuple(p for p in signature.parameters if p not in _COMMON)
        return (*options, "world") if self.other_worlds else options

    def view(self, observation: Any) -> ObservationSpec:
        """The view ``observation`` names (a name, manifest dict or spec); ValueError when it is
        not one this application takes."""
        spec = parse_observation(observation)
        if spec.source_views and not self.has_estimate:
            raise ValueError(f"{self.name} has no source estimate: use observation 'maps' or 'egoR' "
                             f"(R = window radius, e.g. ego9), not {spec.name!r}")
        return spec

    def obs_shape(self, observation: Any, grid: int) -> tuple[int, int, int]:
        """(C, H, W) of one agent's view ``observation`` on a ``grid``×``grid`` area."""
        spec = self.view(observation)
        return spec.shape(grid, len(self.channels(spec)))

    @property
    def views(self) -> tuple[str, ...]:
        """The accepted views ('egoR': any radius)."""
        return OBSERVATION_FORMS if self.has_estimate else ("maps", "egoR")


def _load() -> None:
    """Import the paper's application modules (each registers its descriptor), once."""
    global _loaded
    if _loaded:
        return
    for name in ENV_NAMES:
        importlib.import_module(f"medc_training.envs.{name}")
    others = {n: a for n, a in _REGISTRY.items() if n not in ENV_NAMES}
    ordered = {n: _REGISTRY[n] for n in ENV_NAMES}
    _REGISTRY.clear()
    _REGISTRY.update({**ordered, **others})
    _loaded = True


def applications() -> dict[str, Application]:
    """Every registered application by name (``medc_training.envs.APPLICATIONS``)."""
    _load()
    return _REGISTRY


def register(app: Application) -> Application:
    """Add ``app`` to the registry (ValueError when its name is taken)."""
    if app.name in _REGISTRY:
        raise ValueError(f"application {app.name!r} is registered already")
    _REGISTRY[app.name] = app
    return app


def unregister(name: str) -> None:
    """Remove application ``name`` from the registry."""
    _REGISTRY.pop(name)


def application(name: Any) -> Application:
    """The descriptor of application ``name`` (ValueError for a name this code does not know)."""
    known = applications()
    app = known.get(name) if isinstance(name, str) else None
    if app is None:
        raise ValueError(f"unknown environment {str(name)[:40]!r}; choose one of {', '.join(known)}")
    return app
