"""Target localization's sensing: the sensor model, the team's reading and visit maps, the paper's maps.

The lowest layer of target localization, imported by the environment
(:mod:`medc_training.envs.target_localization`, which re-exports every name here and documents
the reading formula) and by the observation builder (:mod:`medc_training.envs.tl_observation`).
Pure batched functions; the ROS nodes call them on data from topics.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "BACKGROUND",
    "CHANNELS",
    "SOURCE_STRENGTH",
    "VISIT_SATURATION",
    "WALL_ATTENUATION",
    "build_observations",
    "expected_rate_from_sources",
    "normalise_reading",
    "rates_from_every_cell",
    "sensor_reading",
    "update_memory",
    "visit_norm",
]

SOURCE_STRENGTH = 1000.0
WALL_ATTENUATION = 0.5
BACKGROUND = 1.0
VISIT_SATURATION = 10.0
#: The paper's 5 maps, in observation order.
CHANNELS: tuple[str, ...] = ("own_location", "team_locations", "readings", "visit_counts", "walls")

_READING_SCALE = 1.0 / math.log1p(SOURCE_STRENGTH + BACKGROUND)


def normalise_reading(readings: torch.Tensor) -> torch.Tensor:
    """Map raw readings (counts/s) to [0, 1]: log(1 + I) / log(1 + S + BG), clipped."""
    return (torch.log1p(readings) * _READING_SCALE).clamp_(0.0, 1.0)


def sensor_reading(
    positions: torch.Tensor,
    target: torch.Tensor,
    walls: torch.Tensor,
    *,
    noise: bool = False,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Radiation readings (counts/s) of sensors at ``positions`` (formula: module docstring).

    positions: int64 [B,N,2] (row, col) of the N sensors in each of B areas.
    target:    int64 [B,2] source cell.
    walls:     bool [B,H,W] wall cells.
    noise:     draw Poisson counts with the exact reading as mean.
    Returns float32 [B,N].
    """
    rate = expected_rate_from_sources(positions, target.unsqueeze(1), walls)[..., 0]
    if noise:
        rate = torch.poisson(rate, generator=generator)
    return rate


def expected_rate_from_sources(
    positions: torch.Tensor, sources: torch.Tensor, walls: torch.Tensor
) -> torch.Tensor:
    """Noise-free readings (counts/s) at ``positions`` for each candidate source cell.

    positions: int64 [B,N,2] sensor cells; sources: int64 [B,M,2] or [M,2] candidate source
    cells; walls: bool [B,H,W]. Returns float32 [B,N,M]. Entry [b, n, m] is exactly what
    :func:`sensor_reading` returns for a sensor at positions[b, n] and a source at sources[m]
    (the same arithmetic, element by element), so the team's source posterior uses the
    simulator's own sensor model.
    """
    b, n = positions.shape[:2]
    h, w = walls.shape[-2:]
    if sources.dim() == 2:
        sources = sources.unsqueeze(0).expand(b, -1, -1)
    m = sources.shape[1]
    src = sources.to(torch.float32).unsqueeze(1)  # [B,1,M,2]
    delta = positions.to(torch.float32).unsqueeze(2) - src  # [B,N,M,2]
    # H+W samples put consecutive points at most 1/sqrt(2) cell apart, so every crossing of a
    # one-cell-thick wall strip (chord >= 1 cell) is seen; only clipped segment corners can be missed.
    samples = h + w
    t = (torch.arange(samples, device=positions.device, dtype=torch.float32) + 0.5) / samples
    rows = (src[..., 0:1] + delta[..., 0:1] * t).round_()  # [B,N,M,S]
    cols = (src[..., 1:2] + delta[..., 1:2] * t).round_()
    idx = rows.mul_(w).add_(cols).long().view(b, -1)
    inside = walls.reshape(b, -1).gather(1, idx).view(b, n, m, samples)
    # Each run of consecutive wall samples is one wall crossed (the source cell is free).
    entries = inside[..., 0].to(torch.float32) + (inside[..., 1:] > inside[..., :-1]).sum(-1)
    dist2 = (delta * delta).sum(-1)
    return SOURCE_STRENGTH * torch.pow(WALL_ATTENUATION, entries) / (1.0 + dist2) + BACKGROUND


#: Largest (cells² × samples) for which :func:`rates_from_every_cell` keeps a table of the line
#: samples of every (sensor cell, source cell) pair (int64: 64 MiB); larger grids compute them.
_SAMPLE_TABLE_LIMIT = 1 << 23
_SAMPLE_TABLES: dict[tuple[int, int, torch.device], tuple[torch.Tensor, torch.Tensor]] = {}


def _sample_table(h: int, w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(flat cell index of every line sample [H·W, H·W, H+W], squared distance [H·W, H·W]) for
    sensor cell p (first index) and source cell s (second), computed by exactly the arithmetic of
    :func:`expected_rate_from_sources`; None when the table would exceed _SAMPLE_TABLE_LIMIT."""
    cells, samples = h * w, h + w
    if cells * cells * samples > _SAMPLE_TABLE_LIMIT:
        return None
    key = (h, w, device)
    if key not in _SAMPLE_TABLES:
        idx = torch.arange(cells, device=device)
        grid_cells = torch.stack((idx // w, idx % w), dim=-1)
        src = grid_cells.to(torch.float32).unsqueeze(0)  # [1,M,2]
        delta = grid_cells.to(torch.float32).unsqueeze(1) - src  # [P,M,2]
        t = (torch.arange(samples, device=device, dtype=torch.float32) + 0.5) / samples
        rows = (src[..., 0:1] + delta[..., 0:1] * t).round_()
        cols = (src[..., 1:2] + delta[..., 1:2] * t).round_()
        _SAMPLE_TABLES[key] = (rows.mul_(w).add_(cols).long(), (delta * delta).sum(-1))
    return _SAMPLE_TABLES[key]


def rates_from_every_cell(positions: torch.Tensor, walls: torch.Tensor) -> torch.Tensor:
    """float32 [B,N,H·W]: :func:`expected_rate_from_sources` for every cell as a candidate source
    (cells in row-major order), bit for bit. On grids up to 21×21 (_SAMPLE_TABLE_LIMIT) the line
    samples come from a per-grid table made once, which halves the cost; larger grids compute
    them each call."""
    b, n = positions.shape[:2]
    h, w = walls.shape[-2:]
    table = _sample_table(h, w, positions.device)
    if table is None:
        idx = torch.arange(h * w, device=positions.device)
        return expected_rate_from_sources(positions, torch.stack((idx // w, idx % w), dim=-1), walls)
    samples_idx, dist2 = table
    cell = positions[..., 0] * w + positions[..., 1]  # [B,N]
    inside = walls.reshape(b, -1).gather(1, samples_idx[cell].view(b, -1)).view(b, n, h * w, h + w)
    entries = inside[..., 0].to(torch.float32) + (inside[..., 1:] > inside[..., :-1]).sum(-1)
    return SOURCE_STRENGTH * torch.pow(WALL_ATTENUATION, entries) / (1.0 + dist2[cell]) + BACKGROUND


def update_memory(
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    positions: torch.Tensor,
    readings: torch.Tensor,
) -> None:
    """Record the team's new readings, in place.

    reading_map: float32 [B,H,W] latest normalised reading per cell (0 = never visited).
    visit_map:   float32 [B,H,W] number of team visits per cell (raw counts).
    positions:   int64 [B,N,2] where the readings were taken.
    readings:    float32 [B,N] raw readings (counts/s) from :func:`sensor_reading`.
    """
    b = positions.shape[0]
    w = reading_map.shape[-1]
    idx = positions[..., 0] * w + positions[..., 1]
    reading_map.view(b, -1).scatter_(1, idx, normalise_reading(readings))
    visit_map.view(b, -1).scatter_add_(1, idx, torch.ones_like(readings))


def build_observations(
    positions: torch.Tensor,
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    walls: torch.Tensor,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Every agent's 5-map observation (channels: :data:`CHANNELS`).

    positions:   int64 [B,N,2] team positions (row, col).
    reading_map: float32 [B,H,W] from :func:`update_memory`.
    visit_map:   float32 [B,H,W] from :func:`update_memory` (raw counts).
    walls:       bool or float [B,H,W].
    out:         optional float32 [B,N,5,H,W] contiguous tensor to write into.
    Returns float32 [B,N,5,H,W]; agent i's own cell is marked in channel 0 and the cells
    of every other agent in channel 1.
    """
    b, n = positions.shape[:2]
    h, w = walls.shape[-2:]
    hw = h * w
    if out is None:
        out = torch.empty((b, n, 5, h, w), dtype=torch.float32, device=positions.device)
    out[:, :, :2].zero_()
    out[:, :, 2].copy_(reading_map.unsqueeze(1))
    out[:, :, 3].copy_(visit_norm(visit_map).unsqueeze(1))
    out[:, :, 4].copy_(walls.unsqueeze(1))
    cell = positions[..., 0] * w + positions[..., 1]  # [B,N]
    agent_base = (torch.arange(b * n, device=positions.device).view(b, n) * 5) * hw  # [B,N]
    flat = out.view(-1)
    flat.index_fill_(0, (agent_base + cell).view(-1), 1.0)
    if n > 1:
        # Agent i's channel 1 gets every other agent j's cell: index [B, i, j] with j != i.
        others = ~torch.eye(n, dtype=torch.bool, device=positions.device)
        idx = (agent_base + hw).unsqueeze(2) + cell.unsqueeze(1)  # [B,N(i),N(j)]
        flat.index_fill_(0, idx[:, others].view(-1), 1.0)
    return out


def visit_norm(visits: torch.Tensor) -> torch.Tensor:
    """Visit counts divided by VISIT_SATURATION, clipped to 1 (a new tensor)."""
    return (visits * (1.0 / VISIT_SATURATION)).clamp_(max=1.0)
