"""Where the world departs from the model the team and the searchers assume.

The team's estimator and every information-driven searcher assume the benchmark's nominal world:
obstructions that block the line of sight, a detector that counts every gamma the law predicts, a
strength in 100-1000 counts/s and a background in 10-50, readings taken where the agent reports it
is. :class:`Departure` states one way a real site differs, and the benchmark's cores apply it to the
world only (never to the team's model), so the same frozen episodes measure how each policy copes:

- ``transmission``: the fraction of the source's ``S / d²`` an obstruction lets through (0 blocks);
- ``efficiency``: the detector's efficiency relative to the model (every rate times it);
- ``strength_scale``: the source's strength times this (2 puts the strongest twice above the range);
- ``background``: a background of this many counts/s in every episode (None: the episode's own);
- ``position_noise``: the probability that a reading is taken one cell off the reported position
  (a uniformly chosen neighbour that is not an obstruction).

``Departure.parse("transmission=0.3,efficiency=0.7")`` reads the form ``medc-radbench --departure``
takes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch

from medc_training.envs.grid import action_deltas

__all__ = ["Departure", "jittered_positions"]


@dataclass(frozen=True)
class Departure:
    """One departure of the world from the team's model (module docstring); the defaults are none."""

    transmission: float = 0.0
    efficiency: float = 1.0
    strength_scale: float = 1.0
    background: float | None = None
    position_noise: float = 0.0

    def __post_init__(self) -> None:
        checks = (("transmission", self.transmission, 0.0, 1.0), ("efficiency", self.efficiency, 0.01, 10.0),
                  ("strength_scale", self.strength_scale, 0.01, 100.0),
                  ("position_noise", self.position_noise, 0.0, 1.0))
        for name, value, lo, hi in checks:
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
                    or not lo <= value <= hi:
                raise ValueError(f"departure {name} must be a number in [{lo}, {hi}], got {value!r}")
        b = self.background
        if b is not None and (isinstance(b, bool) or not isinstance(b, int | float) or not math.isfinite(b)
                              or not 0.0 <= b <= 10_000.0):
            raise ValueError(f"departure background must be counts/s in [0, 10000] or None, got {b!r}")

    @property
    def nominal(self) -> bool:
        """Whether the world is the model's (no departure)."""
        return self == Departure()

    def to_dict(self) -> dict[str, Any]:
        """The fields that depart from the model (empty when nominal)."""
        default = Departure()
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(default, f.name)}

    @classmethod
    def parse(cls, text: str | None) -> Departure:
        """``"transmission=0.3,efficiency=0.7"`` (or empty / None: nominal). Raises ValueError saying
        what is wrong."""
        if not text:
            return cls()
        names = {f.name for f in dataclasses.fields(cls)}
        values: dict[str, float] = {}
        for item in str(text).split(","):
            key, sep, value = item.strip().partition("=")
            if not sep or key not in names:
                raise ValueError(f"a departure is KEY=NUMBER with KEY one of {', '.join(sorted(names))}, "
                                 f"got {item.strip()[:60]!r}")
            if key in values:
                raise ValueError(f"departure {key} given twice")
            try:
                values[key] = float(value)
            except ValueError:
                raise ValueError(f"departure {key} needs a number, got {value[:40]!r}") from None
        return cls(**values)


def jittered_positions(positions: torch.Tensor, neighbour: torch.Tensor, walls: torch.Tensor) -> torch.Tensor:
    """int64 [K,N,2]: where each reading is taken: ``positions`` moved to neighbour ``neighbour - 1``
    (int64 [K,N], 0 = the reported cell; 1..8 the moves of :data:`~medc_training.envs.grid.ACTIONS`)
    unless that leaves the grid or enters an obstruction (``walls`` bool [K,G,G])."""
    deltas = torch.cat((torch.zeros(1, 2, dtype=torch.long, device=positions.device),
                        action_deltas(positions.device)))
    moved = positions + deltas[neighbour]
    g = walls.shape[-1]
    inside = ((moved >= 0) & (moved < g)).all(-1)
    rows = torch.arange(positions.shape[0], device=positions.device).unsqueeze(1).expand_as(neighbour)
    clamped = moved.clamp(0, g - 1)
    free = inside & ~walls[rows, clamped[..., 0], clamped[..., 1]]
    return torch.where(free.unsqueeze(-1), moved, positions)
