"""The benchmark world's physics as tensors, shared by the cores that play frozen sets
(:class:`~medc_training.radbench.play.BenchCore`) and the training world
(:class:`~medc_training.radbench.world.BenchWorld`): the team's sensor model on the benchmark, the
episodes' layouts as a core takes them, and the world's mean count rates."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from medc_training.envs.grid import bfs_distance
from medc_training.envs.tl_sensing import SensingModel, geometric_factor, parse_sensing, wall_rectangles

__all__ = ["PRIOR_OPTIONS", "TEAM_SENSING", "background_prior", "episode_tensors", "prior_of", "team_sensing",
           "world_rates"]

#: The team's sensor model on the benchmark: the realistic preset (its name, so that bundles trained
#: under it play) with the benchmark's strength range and the 6 x 8 strength x background levels
#: every committed benchmark result used (the preset itself weighs 12 x 16: docs/radbench.md).
TEAM_SENSING: SensingModel = parse_sensing({"name": "realistic", "strength": [100.0, 1000.0],
                                            "levels": [6, 8]})
#: The options that widen (or narrow) the team estimator's background prior, all given or none: the
#: range (counts/s) and its levels. A training world records them (hence a bundle's manifest), and a
#: team whose bundles record them plays under that prior (``medc-radbench --prior-background``).
PRIOR_OPTIONS: tuple[str, str, str] = ("prior_background_low", "prior_background_high",
                                       "prior_background_levels")


def background_prior(given: Any) -> tuple[float, float, int] | None:
    """The checked background prior (low, high, levels) that ``given`` names: a mapping holding the
    keys of :data:`PRIOR_OPTIONS` (all or none; none: None), a sequence (low, high, levels) or a
    string ``"LOW,HIGH,LEVELS"``. Raises ValueError saying what is accepted."""
    if given is None:
        return None
    if isinstance(given, dict):
        present = [k for k in PRIOR_OPTIONS if given.get(k) is not None]
        if not present:
            return None
        if len(present) != len(PRIOR_OPTIONS):
            raise ValueError(f"give {', '.join(PRIOR_OPTIONS)} together (the estimator's background prior)")
        values: Sequence[Any] = [given[k] for k in PRIOR_OPTIONS]
    elif isinstance(given, str):
        values = [v.strip() for v in given.split(",")]
    else:
        values = list(given)
    if len(values) != 3:
        raise ValueError("a background prior is LOW,HIGH,LEVELS (counts/s, counts/s, 2..64), got "
                         f"{str(given)[:60]!r}")
    try:
        low, high = float(values[0]), float(values[1])
        levels_f = float(values[2])
    except (TypeError, ValueError):
        raise ValueError(f"a background prior is LOW,HIGH,LEVELS numbers, got {str(given)[:60]!r}") from None
    if isinstance(values[2], bool) or not levels_f.is_integer() or not 2 <= levels_f <= 64:
        raise ValueError(f"the background prior's levels must be an integer in 2..64, got {values[2]!r}")
    if not (0.0 < low < high <= 10_000.0):
        raise ValueError("the background prior must have 0 < low < high <= 10000 counts/s, "
                         f"got {low:g}, {high:g}")
    return low, high, int(levels_f)


def team_sensing(prior: Any = None) -> SensingModel:
    """The team's sensor model on the benchmark: :data:`TEAM_SENSING`, its background prior replaced
    by ``prior`` (any form :func:`background_prior` reads; None: unchanged). The readings channel's
    scale follows the model's highest rate."""
    checked = background_prior(prior)
    if checked is None:
        return TEAM_SENSING
    low, high, levels = checked
    return parse_sensing({**TEAM_SENSING.to_dict(), "background": [low, high],
                          "levels": [TEAM_SENSING.levels[0], levels]})


def prior_of(sensing: SensingModel) -> tuple[float, float, int] | None:
    """The background prior by which ``sensing`` departs from :data:`TEAM_SENSING` (None: none)."""
    if sensing.background == TEAM_SENSING.background and sensing.levels == TEAM_SENSING.levels:
        return None
    return sensing.background[0], sensing.background[1], sensing.levels[1]


def episode_tensors(episodes: Sequence[Any], grid: int, slots: int, device: torch.device | str
                    ) -> dict[str, torch.Tensor]:
    """The layouts of benchmark ``episodes`` as a core takes them: walls bool [K,G,G], target [K,2],
    positions [K,N,2], distance (BFS to the source) [K,G,G], strength and background float32 [K],
    rects (the walls' rectangles, ``slots`` per episode)."""
    walls = torch.stack([torch.from_numpy(e.walls(grid)) for e in episodes]).to(device)
    target = torch.tensor([e.source for e in episodes], dtype=torch.long, device=device)
    source_map = torch.zeros_like(walls)
    source_map[torch.arange(len(episodes), device=device), target[:, 0], target[:, 1]] = True
    return {
        "walls": walls,
        "target": target,
        "positions": torch.tensor([e.starts for e in episodes], dtype=torch.long, device=device),
        "distance": bfs_distance(~walls, source_map),
        "strength": torch.tensor([e.strength for e in episodes], dtype=torch.float32, device=device),
        "background": torch.tensor([float(e.background) for e in episodes], dtype=torch.float32,
                                   device=device),
        "rects": wall_rectangles(walls, slots),
    }


def world_rates(sensing: SensingModel, cell_m: float, lay: dict[str, torch.Tensor]) -> torch.Tensor:
    """float32 [K,N]: the benchmark world's mean rate (counts/s) at each agent of ``lay`` (positions,
    target, walls, rects, strength, background): ``S / d_m**2 + B`` with d floored at 1 m where the
    line of sight is clear (the exact rule of ``sensing``), ``B`` where an obstruction blocks it. Where
    the world departs from the model (:mod:`~medc_training.radbench.departure`), ``lay`` also holds per
    row the obstructions' ``transmission`` (blocked: ``transmission * S / d² + B``) and the detector's
    ``efficiency`` (every rate times it)."""
    positions, target = lay["positions"], lay["target"]
    factor = geometric_factor(sensing, positions, target.unsqueeze(1), lay["walls"], lay["rects"])[..., 0]
    delta = (positions - target.unsqueeze(1)).to(torch.float32)
    d2_m = (delta * delta).sum(-1) * (cell_m ** 2)
    inverse = 1.0 / d2_m.clamp(min=1.0)
    through = lay.get("transmission")
    blocked = torch.zeros_like(d2_m) if through is None else through.unsqueeze(1) * inverse
    near = torch.where(factor > 0, inverse, blocked)
    rate = lay["strength"].unsqueeze(1) * near + lay["background"].unsqueeze(1)
    efficiency = lay.get("efficiency")
    return rate if efficiency is None else rate * efficiency.unsqueeze(1)
