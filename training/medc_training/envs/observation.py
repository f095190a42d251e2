"""The one observation spec of every application: which view of the state a model takes.

Every core exposes its spec as ``observation`` (and ``observation_name``, ``obs_shape``); bundle
manifests record its name; the agent node, the experts and the run loop ask the spec instead of
checking which application they are in.

Names (written on the command line and as ``observation.name`` in every bundle manifest):

``maps``
    The application's absolute maps, G×G each (the paper's observation).
``egoR``
    Each map in a (2R+1)×(2R+1) window centred on the agent (R = window radius, 1..255).
``maps+estimate`` / ``egoR+estimate``
    The same plus the team's source estimate (an application without one refuses them).

Which views an application takes and the names of their channels are its descriptor's
(:class:`medc_training.envs.Application`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = [
    "MAX_RADIUS",
    "OBSERVATION_NAMES",
    "ObservationSpec",
    "parse_observation",
]

#: Examples of accepted names (any radius 1..MAX_RADIUS is accepted for ego views).
OBSERVATION_NAMES: tuple[str, ...] = ("maps", "maps+estimate", "ego6", "ego6+estimate")
MAX_RADIUS = 255
_NAME = re.compile(r"^(maps|ego([1-9][0-9]{0,2}))(\+estimate)?$")


@dataclass(frozen=True)
class ObservationSpec:
    """Which observation a model takes: ``view`` 'maps' or 'ego', ego ``radius``, ``estimate``."""

    view: str = "maps"
    radius: int = 0
    estimate: bool = False

    def __post_init__(self) -> None:
        if self.view not in ("maps", "ego"):
            raise ValueError(f"observation view must be 'maps' or 'ego', got {self.view!r}")
        if self.view == "ego" and not 1 <= int(self.radius) <= MAX_RADIUS:
            raise ValueError(f"ego observation radius must be 1..{MAX_RADIUS}, got {self.radius!r}")
        if self.view == "maps" and self.radius:
            raise ValueError("the 'maps' observation has no radius")

    @property
    def name(self) -> str:
        base = "maps" if self.view == "maps" else f"ego{self.radius}"
        return base + ("+estimate" if self.estimate else "")

    def side(self, grid: int) -> int:
        """Height and width of one map of this view on a ``grid``×``grid`` area."""
        return grid if self.view == "maps" else 2 * self.radius + 1

    def shape(self, grid: int, channels: int) -> tuple[int, int, int]:
        """(C, H, W) of one agent's observation with ``channels`` maps on a ``grid``×``grid`` area."""
        side = self.side(grid)
        return (int(channels), side, side)

    def __str__(self) -> str:
        return self.name


def parse_observation(value) -> ObservationSpec:
    """An ObservationSpec from a name ('maps', 'ego6+estimate', ...), a manifest dict or a spec."""
    if isinstance(value, ObservationSpec):
        return value
    if isinstance(value, dict):
        value = value.get("name")
    if not isinstance(value, str) or len(value) > 32:
        raise ValueError(f"observation must be a name such as {', '.join(OBSERVATION_NAMES)}")
    m = _NAME.match(value)
    if m is None:
        raise ValueError(
            f"unknown observation {value[:32]!r}; use 'maps', 'maps+estimate', 'egoR' or 'egoR+estimate' "
            "(R = window radius in cells, e.g. ego6+estimate)"
        )
    if m.group(2):
        return ObservationSpec("ego", int(m.group(2)), bool(m.group(3)))
    return ObservationSpec("maps", 0, bool(m.group(3)))
