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
``maps+posterior`` / ``egoR+posterior`` / ``maps+estimate+posterior`` / ``egoR+estimate+posterior``
    The same plus the team's source posterior itself, last (refused where ``+estimate`` is).
``...+information`` (after any of the above, e.g. ``ego6+estimate+posterior+information``)
    The same plus the information a reading would bring at each cell the team can stand on next,
    last (refused where ``+estimate`` is).

Which views an application takes and the names of their channels are its descriptor's
(:class:`medc_training.envs.Application`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = [
    "MAX_NAME_LENGTH",
    "MAX_RADIUS",
    "OBSERVATION_FORMS",
    "OBSERVATION_NAMES",
    "ObservationSpec",
    "parse_observation",
]

#: Examples of accepted names (any radius 1..MAX_RADIUS is accepted for ego views).
OBSERVATION_NAMES: tuple[str, ...] = ("maps", "maps+estimate", "ego6", "ego6+estimate", "ego6+posterior",
                                      "ego6+estimate+posterior")
#: The forms of every accepted name, as error messages list them.
OBSERVATION_FORMS: tuple[str, ...] = ("maps", "egoR", "maps+estimate", "egoR+estimate", "maps+posterior",
                                      "egoR+posterior", "maps+estimate+posterior", "egoR+estimate+posterior",
                                      "egoR+estimate+posterior+information")
MAX_RADIUS = 255
#: Longest name parse_observation reads; the longest accepted one,
#: 'ego255+estimate+posterior+information', fits.
MAX_NAME_LENGTH = 40
_NAME = re.compile(r"^(maps|ego([1-9][0-9]{0,2}))(\+estimate)?(\+posterior)?(\+information)?$")


@dataclass(frozen=True)
class ObservationSpec:
    """Which observation a model takes: ``view`` 'maps' or 'ego', ego ``radius``, whether it shows
    the team's source ``estimate``, its source ``posterior`` and the ``information`` of a reading at
    the cells the team can stand on next."""

    view: str = "maps"
    radius: int = 0
    estimate: bool = False
    posterior: bool = False
    information: bool = False

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
        return (base + ("+estimate" if self.estimate else "") + ("+posterior" if self.posterior else "")
                + ("+information" if self.information else ""))

    @property
    def source_views(self) -> bool:
        """Whether it shows any of the team's source maps (estimate, posterior, information)."""
        return self.estimate or self.posterior or self.information

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
    if not isinstance(value, str) or len(value) > MAX_NAME_LENGTH:
        raise ValueError(f"observation must be a name such as {', '.join(OBSERVATION_NAMES)}")
    m = _NAME.match(value)
    if m is None:
        forms = ", ".join(repr(f) for f in OBSERVATION_FORMS)
        raise ValueError(
            f"unknown observation {value[:MAX_NAME_LENGTH]!r}; use one of {forms} (R = window radius in "
            "cells, e.g. ego6+estimate; +estimate comes before +posterior, +information last)"
        )
    estimate, posterior, information = bool(m.group(3)), bool(m.group(4)), bool(m.group(5))
    if m.group(2):
        return ObservationSpec("ego", int(m.group(2)), estimate, posterior, information)
    return ObservationSpec("maps", 0, estimate, posterior, information)
