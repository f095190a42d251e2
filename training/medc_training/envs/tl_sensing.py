"""Target localization's sensing: the sensor model, the team's reading and visit maps, the paper's maps.

The lowest layer of target localization, imported by the environment
(:mod:`medc_training.envs.target_localization`, which re-exports every name here and documents
the reading formula) and by the observation builder (:mod:`medc_training.envs.tl_observation`).
Pure batched functions; the ROS nodes call them on data from topics.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch

from medc_training.envs.grid import grid_cells

__all__ = [
    "BACKGROUND",
    "CHANNELS",
    "DEFAULT_SENSING",
    "SENSING_PRESETS",
    "SOURCE_STRENGTH",
    "VISIT_SATURATION",
    "WALL_ATTENUATION",
    "SensingModel",
    "build_observations",
    "expected_rate_from_sources",
    "geometric_factor",
    "normalise_reading",
    "parse_sensing",
    "rates_from_every_cell",
    "realistic_rates",
    "sampled_rate_table",
    "segment_crossings",
    "sensor_reading",
    "update_memory",
    "visit_norm",
    "wall_rectangles",
    "wall_segments",
]

SOURCE_STRENGTH = 1000.0
WALL_ATTENUATION = 0.5
BACKGROUND = 1.0
VISIT_SATURATION = 10.0
#: The paper's 5 maps, in observation order.
CHANNELS: tuple[str, ...] = ("own_location", "team_locations", "readings", "visit_counts", "walls")

_READING_SCALE = 1.0 / math.log1p(SOURCE_STRENGTH + BACKGROUND)


def normalise_reading(readings: torch.Tensor, max_rate: float | None = None) -> torch.Tensor:
    """Map raw readings (counts/s) to [0, 1]: log(1 + I) / log(1 + max_rate), clipped; the
    paper-simple model's highest rate S + BG unless ``max_rate`` is given (a sensing model's
    :attr:`SensingModel.max_rate`)."""
    scale = _READING_SCALE if max_rate is None else 1.0 / math.log1p(max_rate)
    return (torch.log1p(readings) * scale).clamp_(0.0, 1.0)


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


#: Largest grid (cells per side) whose crossing tables (:func:`crossing_tables`) are kept:
#: 2 × G⁵ × 2 bytes, 30 -> 93 MiB, 32 -> 128 MiB. Larger grids sample every line each call.
_CROSSING_TABLE_GRID = 32
_CROSSING_TABLES: dict[tuple[int, torch.device], torch.Tensor] = {}


def crossing_tables(g: int, device: torch.device) -> torch.Tensor | None:
    """Where the sampled line between two cells runs, per row and per column of a G×G grid.

    int8 [2, G², G, 2, G²]: entries [0, p, r, :, s] are the (smallest, largest) column among the
    line's samples that fall on row r, for the line from source cell s to sensor cell p sampled
    exactly as :func:`expected_rate_from_sources` samples it; entries [1, p, c, :, s] the
    (smallest, largest) row among the samples in column c; (G, -1) where no sample falls. Every
    source cell of one (orientation, sensor cell, line) is one contiguous block. Made once per
    grid (a few seconds at G = 30); None above _CROSSING_TABLE_GRID.

    Why this is enough (:func:`segment_crossings`): a sample's row and column are rounded values of
    float32 expressions that are monotone in the sample index, so the samples inside one
    axis-aligned wall segment are consecutive; consecutive samples are at most one cell apart in
    each coordinate (the step is below half a cell), and segments never touch, so the samples of
    two segments never join into one run. The sampled rule's count of wall runs is therefore the
    number of segments the samples meet, and a sample meets a horizontal segment on row r with
    columns c0..c1 exactly when the row-r column range overlaps c0..c1.
    """
    if g > _CROSSING_TABLE_GRID:
        return None
    key = (g, device)
    if key not in _CROSSING_TABLES:
        cells = g * g
        samples = 2 * g
        every = grid_cells(g, device)
        src = every.to(torch.float32).unsqueeze(0)  # [1,M,2]
        t = (torch.arange(samples, device=device, dtype=torch.float32) + 0.5) / samples
        table = torch.empty((2, cells, g, 2, cells), dtype=torch.int8, device=device)
        chunk = max(1, (1 << 21) // (cells * samples))  # sensor cells per chunk (~2M samples)
        for lo in range(0, cells, chunk):
            hi = min(cells, lo + chunk)
            delta = every[lo:hi].to(torch.float32).unsqueeze(1) - src  # [P,M,2]
            rows = (src[..., 0:1] + delta[..., 0:1] * t).round_().long()  # [P,M,S]
            cols = (src[..., 1:2] + delta[..., 1:2] * t).round_().long()
            for orient, (line, value) in enumerate(((rows, cols), (cols, rows))):
                shape = (hi - lo, cells, g)
                least = torch.full(shape, g, dtype=torch.long, device=device)
                most = torch.full(shape, -1, dtype=torch.long, device=device)
                least.scatter_reduce_(2, line, value, reduce="amin")
                most.scatter_reduce_(2, line, value, reduce="amax")
                table[orient, lo:hi, :, 0] = least.transpose(1, 2).to(torch.int8)
                table[orient, lo:hi, :, 1] = most.transpose(1, 2).to(torch.int8)
        _CROSSING_TABLES[key] = table
    return _CROSSING_TABLES[key]


def wall_segments(walls: torch.Tensor, most: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(int64 [B,most,4], bool [B]): each map's wall segments as (first row, first column, last row,
    last column), and whether the map is made of at most ``most`` one-cell-thick segments that never
    touch, as every generated layout is (an operator's own map may not be). Only then is the
    sampled rule's count of wall runs the number of segments met (:func:`segment_crossings`).
    Empty slots are (-1, -1, -2, -2) and meet nothing."""
    walls = walls.bool()
    b = walls.shape[0]
    rects = wall_rectangles(walls)  # as many slots as the fullest map needs
    empty = rects[..., 2] < rects[..., 0]
    segs = torch.stack((rects[..., 0] + 0.5, rects[..., 1] + 0.5, rects[..., 2] - 0.5,
                        rects[..., 3] - 0.5), -1).round_().long()
    segs[empty] = torch.tensor([-1, -1, -2, -2], device=segs.device)
    ok = _segments_are_the_walls(walls, segs, empty) & ((~empty).sum(1) <= most)
    out = torch.tensor([-1, -1, -2, -2], device=segs.device).repeat(b, max(1, most), 1)
    keep = min(out.shape[1], segs.shape[1])
    out[:, :keep] = segs[:, :keep]
    return out, ok


def _segments_are_the_walls(walls: torch.Tensor, segs: torch.Tensor, empty: torch.Tensor) -> torch.Tensor:
    """bool [B]: whether ``segs`` paint exactly ``walls``, each is one cell thick, and no two touch
    (their Chebyshev gap is at least one free cell)."""
    _b, h, w = walls.shape
    rows = torch.arange(h, device=walls.device)
    cols = torch.arange(w, device=walls.device)
    in_r = (rows >= segs[..., 0:1]) & (rows <= segs[..., 2:3])  # [B,Z,H]
    in_c = (cols >= segs[..., 1:2]) & (cols <= segs[..., 3:4])
    painted = (in_r.unsqueeze(-1) & in_c.unsqueeze(-2)).any(1)
    ok = (painted == walls).flatten(1).all(1)
    ok &= ((segs[..., 0] == segs[..., 2]) | (segs[..., 1] == segs[..., 3]) | empty).all(1)
    a, c = segs.unsqueeze(2), segs.unsqueeze(1)  # [B,Z,1,4], [B,1,Z,4]
    gap = torch.maximum(torch.maximum(c[..., 0] - a[..., 2], a[..., 0] - c[..., 2]),
                        torch.maximum(c[..., 1] - a[..., 3], a[..., 1] - c[..., 3]))
    both = ~(empty.unsqueeze(2) | empty.unsqueeze(1))
    both &= ~torch.eye(segs.shape[1], dtype=torch.bool, device=walls.device)
    return ok & ~(both & (gap <= 1)).flatten(1).any(1)


def segment_crossings(positions: torch.Tensor, segments: torch.Tensor, grid: int) -> torch.Tensor | None:
    """int32 [B,N,G²]: the sampled rule's count of walls crossed between each sensor at
    ``positions`` (int64 [B,N,2]) and every cell as a candidate source, from the crossing tables
    (:func:`crossing_tables`): O(G² · segments) per sensor instead of O(G³). ``segments`` from
    :func:`wall_segments`. None above _CROSSING_TABLE_GRID."""
    table = crossing_tables(grid, positions.device)
    if table is None:
        return None
    b, n = positions.shape[:2]
    cell = positions[..., 0] * grid + positions[..., 1]  # [B,N]
    if segments.shape[1] == 0:
        return torch.zeros((b, n, grid * grid), dtype=torch.int32, device=positions.device)
    horizontal = segments[..., 0] == segments[..., 2]  # [B,Z] (a 1x1 segment: either test holds)
    orient = (~horizontal).long()
    line = torch.where(horizontal, segments[..., 0], segments[..., 1]).clamp(min=0)
    lo = torch.where(horizontal, segments[..., 1], segments[..., 0])
    hi = torch.where(horizontal, segments[..., 3], segments[..., 2])
    cells = grid * grid
    row = (orient.unsqueeze(1) * cells + cell.unsqueeze(2)) * grid + line.unsqueeze(1)  # [B,N,Z]
    span = table.view(-1, 2 * cells).index_select(0, row.view(-1)).view(b, n, -1, 2, cells)
    met = (span[..., 0, :] <= hi.view(b, 1, -1, 1).to(torch.int8)).logical_and_(
        span[..., 1, :] >= lo.view(b, 1, -1, 1).to(torch.int8))
    return met.sum(2, dtype=torch.int32)


def sampled_rate_table(grid: int, most: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(rate float32 [Q], log rate float32 [Q]) of the paper-simple model for Q = (walls crossed k
    in 0..most) x (d² in 0..2(G-1)²), index k * (2(G-1)² + 1) + d²: the arithmetic of
    :func:`expected_rate_from_sources`, element by element, so a lookup equals the computed rate
    bit for bit."""
    span = 2 * (grid - 1) ** 2 + 1
    q = torch.arange(span * (most + 1), device=device)
    crossed, dist2 = (q // span).to(torch.float32), (q % span).to(torch.float32)
    rate = SOURCE_STRENGTH * torch.pow(WALL_ATTENUATION, crossed) / (1.0 + dist2) + BACKGROUND
    return rate, torch.log(rate)


def rates_from_every_cell(positions: torch.Tensor, walls: torch.Tensor) -> torch.Tensor:
    """float32 [B,N,H·W]: :func:`expected_rate_from_sources` for every cell as a candidate source
    (cells in row-major order), every line sampled. (Maps made of wall segments take the crossing
    tables instead: :func:`segment_crossings` and :func:`sampled_rate_table`.)"""
    h, w = walls.shape[-2:]
    idx = torch.arange(h * w, device=positions.device)
    return expected_rate_from_sources(positions, torch.stack((idx // w, idx % w), dim=-1), walls)


def update_memory(
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    positions: torch.Tensor,
    readings: torch.Tensor,
    max_rate: float | None = None,
) -> None:
    """Record the team's new readings, in place (``max_rate``: see :func:`normalise_reading`).

    reading_map: float32 [B,H,W] latest normalised reading per cell (0 = never visited).
    visit_map:   float32 [B,H,W] number of team visits per cell (raw counts).
    positions:   int64 [B,N,2] where the readings were taken.
    readings:    float32 [B,N] raw readings (counts/s) from :func:`sensor_reading`.
    """
    b = positions.shape[0]
    w = reading_map.shape[-1]
    idx = positions[..., 0] * w + positions[..., 1]
    reading_map.view(b, -1).scatter_(1, idx, normalise_reading(readings, max_rate))
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


# ------------------------------------------------------------------------------------------
# Sensing presets: the paper's simple model, and the field's realistic one
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensingModel:
    """How readings are made, and what the team knows of it (environment option ``sensing``).

    The rate at cell p, from a source of strength S at cell s, with background B::

        lambda(p) = S * A**k(p, s) / (1 + d(p, s)**2) + B

    d in cells (one cell = ``cell_size_m`` metres); A = ``attenuation`` per obstruction the line
    of sight crosses (0: an obstruction blocks it, the reading is background only); k counted by
    the ``line`` rule: ``sampled`` (the paper-simple preset's rule: H+W samples along the line,
    docs/ros-reference.md, "Sensor model") or ``exact`` (the segment between the two cell centres
    against each wall segment's rectangle: exact geometry, O(walls) per pair).

    S is drawn per episode uniformly from ``strength`` and B from ``background`` (a range with
    equal ends is a known constant). With ``noise`` True readings are Poisson counts in one
    second; False leaves it to the environment's ``noise`` option (the paper-simple preset only).
    An episode succeeds when an agent is within ``success_radius`` cells (Euclidean) of the source.
    The team's estimator marginalises S and B over ``levels`` = (strength levels, background
    levels): the midpoints of equal-width bins of each range (a range with equal ends: one level).
    """

    name: str
    strength: tuple[float, float]
    background: tuple[float, float]
    attenuation: float
    noise: bool
    success_radius: float
    line: str
    levels: tuple[int, int]
    cell_size_m: float = 1.0

    def __post_init__(self) -> None:
        for label, (lo, hi) in (("strength", self.strength), ("background", self.background)):
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 1e9):
                raise ValueError(f"sensing {label} must be a range 0 <= lo <= hi <= 1e9, got {(lo, hi)}")
        if self.background[0] <= 0.0:
            raise ValueError("sensing background must be > 0 (a Poisson likelihood needs a positive rate)")
        if not 0.0 <= self.attenuation <= 1.0:
            raise ValueError(f"sensing attenuation must be in [0, 1], got {self.attenuation}")
        if not 0.0 <= self.success_radius <= 64.0:
            raise ValueError(f"sensing success_radius must be in [0, 64] cells, got {self.success_radius}")
        if self.line not in ("sampled", "exact"):
            raise ValueError(f"sensing line must be 'sampled' or 'exact', got {self.line!r}")
        ns, nb = self.levels
        if not (1 <= ns <= 64 and 1 <= nb <= 64):
            raise ValueError(f"sensing levels must be two integers in 1..64, got {self.levels}")
        fixed_s, fixed_b = self.strength[0] == self.strength[1], self.background[0] == self.background[1]
        if fixed_s != (ns == 1) or fixed_b != (nb == 1):
            raise ValueError("sensing levels: a known (fixed) strength or background takes exactly 1 level, "
                             "an unknown one at least 2")

    def within_reach(self, dist2: torch.Tensor) -> torch.Tensor:
        """bool, same shape: whether an agent at squared distance ``dist2`` (cells², integers) from
        the source has found it: d <= ``success_radius`` (radius 0: only on the source's cell). The
        one success rule of the environment, the team's estimator and the controllers."""
        return dist2 <= self.success_radius * self.success_radius

    @property
    def known(self) -> bool:
        """Whether the team knows the source's strength and the background (one level each)."""
        return self.levels == (1, 1)

    @property
    def max_rate(self) -> float:
        """The highest rate of the model (on the source, strongest source, highest background)."""
        return self.strength[1] + self.background[1]

    def strength_levels(self, device: torch.device | str = "cpu") -> torch.Tensor:
        """float32 [ns]: the strengths the estimator weighs (bin midpoints of the range)."""
        return _midpoints(self.strength, self.levels[0], device)

    def background_levels(self, device: torch.device | str = "cpu") -> torch.Tensor:
        """float32 [nb]: the backgrounds the estimator weighs."""
        return _midpoints(self.background, self.levels[1], device)

    def level_values(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """(strength, background) float32 [ns * nb] of each level of the estimator's joint posterior,
        strength-major (level i: strength i // nb, background i % nb)."""
        s_lv, b_lv = self.strength_levels(device), self.background_levels(device)
        return s_lv.repeat_interleave(len(b_lv)), b_lv.repeat(len(s_lv))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (bundle manifests record it; :func:`parse_sensing` reads it back)."""
        d = asdict(self)
        for key in ("strength", "background", "levels"):
            d[key] = list(d[key])
        return d


def _midpoints(bounds: tuple[float, float], count: int, device: torch.device | str) -> torch.Tensor:
    lo, hi = bounds
    width = (hi - lo) / count
    values = [lo] if count == 1 else [lo + width * (i + 0.5) for i in range(count)]
    return torch.tensor(values, dtype=torch.float32, device=device)


#: The named presets. ``paper-simple`` is the model every committed result used (a strong source
#: of known strength, background 1, walls halve the rate); ``realistic`` follows RAD-A2C's published
#: ranges (Proctor et al. 2021: 20 m x 20 m area, 1 m moves; source 1e6-1e7 counts/s at 1 cm, i.e.
#: 100-1000 counts/s at 1 m; background 10-50 counts/s; Poisson counts every step; obstructions
#: that block the line of sight; success within 1.1 m). With one cell = 1 m and the 1/(1 + d^2)
#: law, a strength of 200-2000 gives 100-1000 counts/s at 1 m and 2-20 at 10 m. Its estimator
#: weighs 12 x 16 strength x background levels: the coarsest grid measured to keep the team's
#: declarations as right as they claim (docs/reproduction/calibration/README.md; 6 x 8 declared a
#: wrong cell at mass >= 0.99 in 2-5 % of the episodes).
SENSING_PRESETS: dict[str, SensingModel] = {
    "paper-simple": SensingModel(
        name="paper-simple", strength=(SOURCE_STRENGTH, SOURCE_STRENGTH), background=(BACKGROUND, BACKGROUND),
        attenuation=WALL_ATTENUATION, noise=False, success_radius=0.0, line="sampled", levels=(1, 1),
        cell_size_m=1.0,
    ),
    "realistic": SensingModel(
        name="realistic", strength=(200.0, 2000.0), background=(10.0, 50.0), attenuation=0.0, noise=True,
        success_radius=1.1, line="exact", levels=(12, 16), cell_size_m=1.0,
    ),
}
DEFAULT_SENSING = "paper-simple"
_SENSING_FIELDS = {"name", "strength", "background", "attenuation", "noise", "success_radius", "line",
                   "levels", "cell_size_m"}


def parse_sensing(value: Any) -> SensingModel:
    """A SensingModel from a preset name, a dict (a manifest's ``sensing``: a preset's name with
    any fields overridden) or a model. Raises ValueError saying what is accepted."""
    if isinstance(value, SensingModel):
        return value
    if isinstance(value, str):
        if value not in SENSING_PRESETS:
            raise ValueError(f"unknown sensing preset {value[:40]!r}; "
                             f"choose one of {sorted(SENSING_PRESETS)}")
        return SENSING_PRESETS[value]
    if isinstance(value, dict):
        unknown = set(value) - _SENSING_FIELDS
        if unknown:
            raise ValueError(f"sensing: unknown fields {sorted(str(k)[:40] for k in unknown)}; "
                             f"known: {sorted(_SENSING_FIELDS)}")
        base = SENSING_PRESETS.get(value.get("name", DEFAULT_SENSING))
        if base is None:
            raise ValueError(f"sensing: name must be one of {sorted(SENSING_PRESETS)}")
        fields = base.to_dict()
        fields.update(value)
        try:
            return SensingModel(
                name=str(fields["name"]),
                strength=(float(fields["strength"][0]), float(fields["strength"][1])),
                background=(float(fields["background"][0]), float(fields["background"][1])),
                attenuation=float(fields["attenuation"]), noise=bool(fields["noise"]),
                success_radius=float(fields["success_radius"]), line=str(fields["line"]),
                levels=(int(fields["levels"][0]), int(fields["levels"][1])),
                cell_size_m=float(fields["cell_size_m"]),
            )
        except (TypeError, IndexError, KeyError) as exc:
            raise ValueError(f"sensing: malformed field ({type(exc).__name__})") from None
    raise ValueError(f"sensing must be a preset name ({', '.join(sorted(SENSING_PRESETS))}) or a dict")


def wall_rectangles(walls: torch.Tensor, most: int | None = None) -> torch.Tensor:
    """float32 [B,most,4]: each wall segment of ``walls`` (bool [B,H,W]) as the rectangle
    (top, left, bottom, right) its cells cover, in cell-centre coordinates (row - 0.5 .. row + 0.5);
    unused slots are an empty rectangle far off the grid. ``most`` None: as many slots as the
    fullest map has wall cells (a segment has at least one), at least 1.

    Walls never touch (not even diagonally), so every 8-connected group of wall cells is one
    axis-aligned segment: its top-left cell has no wall above or to the left, and the segment runs
    right or down from it.
    """
    b, _h, w = walls.shape
    walls = walls.bool()
    if most is None:
        most = max(1, int(walls.flatten(1).sum(1).max()) if b else 1)
    up = torch.nn.functional.pad(walls, (0, 0, 1, 0))[:, :-1]
    left = torch.nn.functional.pad(walls, (1, 0, 0, 0))[:, :, :-1]
    corner = walls & ~up & ~left  # [B,H,W]
    # Run length down and right from every cell (walls are straight, so one of them is 1).
    down_run = _run_length(walls.transpose(1, 2)).transpose(1, 2)
    right_run = _run_length(walls)
    count = corner.flatten(1).sum(1)
    if b and int(count.max()) > most:
        raise ValueError(f"the map has more than {most} wall segments")
    rects = torch.full((b, most, 4), -1e6, dtype=torch.float32, device=walls.device)
    rects[..., 2:] = -1e6 - 1.0  # empty: bottom < top
    order = torch.argsort(corner.flatten(1).float(), dim=1, descending=True, stable=True)[:, :most]
    valid = corner.flatten(1).gather(1, order)
    r0 = (order // w).float()
    c0 = (order % w).float()
    dr = down_run.flatten(1).gather(1, order).float()
    dc = right_run.flatten(1).gather(1, order).float()
    found = torch.stack((r0 - 0.5, c0 - 0.5, r0 + dr - 0.5, c0 + dc - 0.5), -1)
    k = order.shape[1]  # most, or every cell of a map smaller than that
    rects[:, :k] = torch.where(valid.unsqueeze(-1), found, rects[:, :k])
    return rects


def _run_length(walls: torch.Tensor) -> torch.Tensor:
    """int64 [B,H,W]: how many wall cells run rightwards from each cell (0 on free cells)."""
    w = walls.shape[-1]
    out = torch.zeros(walls.shape, dtype=torch.long, device=walls.device)
    run = torch.zeros(walls.shape[:-1], dtype=torch.long, device=walls.device)
    for c in range(w - 1, -1, -1):
        run = torch.where(walls[..., c], run + 1, 0)
        out[..., c] = run
    return out


#: Largest grid (cells per side) whose pair tables (:func:`_pair_tables`) are kept: 48 -> 64 MiB.
_PAIR_TABLE_GRID = 48
_PAIR_TABLES: dict[tuple[int, int, torch.device], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}


def _pair_tables(h: int, w: int,
                 device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """(1 / (s - p) per axis float32 [H·W, H·W, 2] (inf where equal), 1 / (1 + d²) float32
    [H·W, H·W], d² int64 [H·W, H·W]) for sensor cell p (first index) and source cell s; None above
    _PAIR_TABLE_GRID."""
    if max(h, w) > _PAIR_TABLE_GRID:
        return None
    key = (h, w, device)
    if key not in _PAIR_TABLES:
        idx = torch.arange(h * w, device=device)
        cells = torch.stack((idx // w, idx % w), dim=-1)
        delta = (cells.unsqueeze(0) - cells.unsqueeze(1)).to(torch.float32)  # [P,S,2]: s - p
        d2 = ((cells.unsqueeze(0) - cells.unsqueeze(1)) ** 2).sum(-1)
        _PAIR_TABLES[key] = (1.0 / delta, 1.0 / (1.0 + d2.to(torch.float32)), d2)
    return _PAIR_TABLES[key]


def sight_lines(model: SensingModel, positions: torch.Tensor, walls: torch.Tensor,
                rects: torch.Tensor, fused: bool = False) -> tuple[torch.Tensor, torch.Tensor] | None:
    """For every sensor at ``positions`` (int64 [B,N,2]) and every cell of the grid as a candidate
    source, under the ``exact`` line rule: (d² int64 [B,N,H·W], walls crossed int64 [B,N,H·W];
    with attenuation 0 only whether any is, 0 or 1), so that the factor is A**k / (1 + d²). None
    where the per-grid tables are not kept (grids above _PAIR_TABLE_GRID). ``fused``: the same
    values from :func:`_blocked_exact` (no tables; any grid)."""
    h, w = walls.shape[-2:]
    if fused:
        rows, cols = _cell_coordinates(h, w, positions.device)
        p = positions.to(torch.float32)
        d2 = ((rows - p[..., 0:1]).square_() + (cols - p[..., 1:2]).square_()).long()  # exact: small integers
        crossed = _blocked_exact(positions, rects, h, w, count=model.attenuation > 0.0)
        return d2, crossed.long()
    tables = _pair_tables(h, w, positions.device)
    if tables is None:
        return None
    cell = positions[..., 0] * w + positions[..., 1]
    d2 = tables[2][cell]
    if not bool((rects[..., 2] > rects[..., 0]).any()):
        return d2, torch.zeros_like(d2)
    crossed = _blocked(positions, tables[0][cell], rects, count=model.attenuation > 0.0)
    return d2, crossed.long()


#: Shortest part of a segment (as a fraction of its length) inside a wall's rectangle that counts as
#: running through it (below: it only grazes a corner, as exact arithmetic would find).
_GRAZE = 1e-5


def _blocked(positions: torch.Tensor, inv: torch.Tensor, rects: torch.Tensor, count: bool) -> torch.Tensor:
    """[B,N,M]: how many wall rectangles (``count``) or whether any (not ``count``) the segment
    from each sensor cell to each candidate source cell passes through: the open segment against
    each open rectangle, by the slab method.

    positions int64 [B,N,2]; inv float32 [B,N,M,2] = 1 / (s - p) per axis (inf where equal);
    rects float32 [B,Z,4] (top, left, bottom, right). Cell centres are integers and rectangle sides
    half-integers, so no centre lies on a side and no 0 * inf arises. Candidates are the innermost
    dimension of every temporary, so each operation runs over contiguous memory.
    """
    b, n = positions.shape[:2]
    p = positions.to(torch.float32).view(b, n, 1, 2)
    lo = (rects[:, None, :, 0:2] - p).unsqueeze(-1)  # [B,N,Z,2,1]: lo - p per axis
    hi = (rects[:, None, :, 2:4] - p).unsqueeze(-1)
    inv_r = inv[..., 0].unsqueeze(2)  # [B,N,1,M]
    inv_c = inv[..., 1].unsqueeze(2)
    a_r, b_r = lo[..., 0, :] * inv_r, hi[..., 0, :] * inv_r  # [B,N,Z,M]
    a_c, b_c = lo[..., 1, :] * inv_c, hi[..., 1, :] * inv_c
    enter = torch.maximum(torch.minimum(a_r, b_r), torch.minimum(a_c, b_c)).clamp_(min=0.0)
    leave = torch.minimum(torch.maximum(a_r, b_r), torch.maximum(a_c, b_c)).clamp_(max=1.0)
    # A segment that only touches a corner has enter == leave exactly; float32 rounding (about
    # 1e-7 here) must not make it a crossing, while a real crossing of a rectangle with half-integer
    # sides by a segment between integer points lasts far longer than _GRAZE (about 1e-4 of the
    # segment at G = 48).
    hit = enter + _GRAZE < leave  # [B,N,Z,M]
    return hit.sum(2, dtype=torch.float32) if count else hit.any(2)


_CELL_COORDINATES: dict[tuple[int, int, torch.device], tuple[torch.Tensor, torch.Tensor]] = {}

#: Episodes per chunk of :func:`_blocked_exact` (its [chunk, N, Z, H·W] temporaries stay in a core's
#: L2 cache at 20×20).
_EXACT_CHUNK = 32


def _cell_coordinates(h: int, w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(row float32 [H·W], column float32 [H·W]) of every cell, row-major."""
    key = (h, w, device)
    if key not in _CELL_COORDINATES:
        idx = torch.arange(h * w, device=device)
        _CELL_COORDINATES[key] = ((idx // w).to(torch.float32), (idx % w).to(torch.float32))
    return _CELL_COORDINATES[key]


def _blocked_exact(positions: torch.Tensor, rects: torch.Tensor, h: int, w: int, count: bool) -> torch.Tensor:
    """:func:`_blocked` for every cell of the grid as a candidate source, by the separating-axis test
    in exact arithmetic: [B,N,H·W] walls crossed (``count``, float32) or whether any is (bool).

    The segment from sensor cell p to candidate cell s (the closed segment; cell centres are integers)
    meets the open rectangle (top, left, bottom, right) (half-integer sides) exactly when no axis
    separates them: along the rows, max(p_r, s_r) > top and min(p_r, s_r) < bottom (likewise along
    the columns), and along the segment's normal |d × (c - p)| < |d_c| h_r + |d_r| h_c, with d = s - p,
    c the rectangle's centre and h its half sides. On a grid of up to 2^10 cells a side every quantity
    is a multiple of 1/2 below 2^22, so float32 computes it exactly (an empty slot, far off the grid,
    fails the row test whatever its other margins), and the test is the exact answer that
    :func:`_blocked` reaches with its graze margin (tested on every sensor/source pair of random
    layouts): a corner touch or a run along a side is no crossing. Computed as one margin per
    (sensor, rectangle, cell), the least of the five, positive exactly when the segment runs through
    the rectangle; a chunk of episodes at a time.
    """
    b, n = positions.shape[:2]
    rows, cols = _cell_coordinates(h, w, positions.device)  # [S]
    p = positions.to(torch.float32)
    py, px = p[..., 0:1], p[..., 1:2]  # [B,N,1]
    top, left, bottom, right = (r.reshape(b, 1, -1, 1) for r in rects.unbind(-1))  # [B,1,Z,1]
    cy = (top + bottom) * 0.5 - py.unsqueeze(-1)  # [B,N,Z,1]: the centre relative to the sensor
    cx = (left + right) * 0.5 - px.unsqueeze(-1)
    hy, hx = (bottom - top) * 0.5, (right - left) * 0.5  # [B,1,Z,1]
    out = torch.empty((b, n, h * w), dtype=torch.float32 if count else torch.bool, device=positions.device)
    for s in range(0, b, _EXACT_CHUNK):
        e = min(b, s + _EXACT_CHUNK)
        dy = (rows - py[s:e]).unsqueeze(2)  # [k,N,1,S]
        dx = (cols - px[s:e]).unsqueeze(2)
        margin = (dx.abs() * hy[s:e]).add_(dy.abs() * hx[s:e])  # [k,N,Z,S]
        margin.sub_((dx * cy[s:e]).sub_(dy * cx[s:e]).abs_())
        torch.minimum(margin, torch.maximum(rows, py[s:e]).unsqueeze(2) - top[s:e], out=margin)
        torch.minimum(margin, bottom[s:e] - torch.minimum(rows, py[s:e]).unsqueeze(2), out=margin)
        torch.minimum(margin, torch.maximum(cols, px[s:e]).unsqueeze(2) - left[s:e], out=margin)
        torch.minimum(margin, right[s:e] - torch.minimum(cols, px[s:e]).unsqueeze(2), out=margin)
        if count:
            torch.sum(margin > 0, 2, dtype=torch.float32, out=out[s:e])
        else:
            torch.gt(margin.amax(2), 0, out=out[s:e])
    return out


def geometric_factor(model: SensingModel, positions: torch.Tensor, sources: torch.Tensor,
                     walls: torch.Tensor, rects: torch.Tensor | None = None) -> torch.Tensor:
    """float32 [B,N,M]: A**k / (1 + d^2) for each sensor cell and candidate source cell, so that the
    rate is S * factor + B. ``sources`` int64 [B,M,2], or [M,2] for the same cells in every area
    (every cell of the grid in row-major order takes per-grid tables). ``rects`` (from
    :func:`wall_rectangles`; made from ``walls`` when None) for the ``exact`` line rule; the
    ``sampled`` rule reads ``walls``."""
    if model.line == "sampled":
        rate = expected_rate_from_sources(positions, sources, walls)
        return (rate - BACKGROUND) / SOURCE_STRENGTH
    b = positions.shape[0]
    h, w = walls.shape[-2:]
    every_cell = sources.dim() == 2 and len(sources) == h * w
    tables = _pair_tables(h, w, positions.device) if every_cell else None
    if tables is not None:
        cell = positions[..., 0] * w + positions[..., 1]
        inv, near = tables[0][cell], tables[1][cell]  # [B,N,M,2], [B,N,M]
    else:
        if sources.dim() == 2:
            sources = sources.unsqueeze(0).expand(b, -1, -1)
        delta = sources.to(torch.float32).unsqueeze(1) - positions.to(torch.float32).unsqueeze(2)
        inv, near = 1.0 / delta, 1.0 / (1.0 + (delta * delta).sum(-1))
    if rects is None:
        rects = wall_rectangles(walls)
    if not bool((rects[..., 2] > rects[..., 0]).any()):  # no walls anywhere: nothing in the way
        return near
    if model.attenuation == 0.0:
        return near.masked_fill(_blocked(positions, inv, rects, count=False), 0.0)
    crossed = _blocked(positions, inv, rects, count=True)
    return near * torch.pow(torch.tensor(model.attenuation, device=near.device), crossed)


def realistic_rates(model: SensingModel, positions: torch.Tensor, target: torch.Tensor, walls: torch.Tensor,
                    strength: torch.Tensor, background: torch.Tensor,
                    rects: torch.Tensor | None = None) -> torch.Tensor:
    """float32 [B,N]: the mean rate (counts/s) at each sensor for the episode's source (cell
    ``target`` int64 [B,2], ``strength`` and ``background`` float32 [B])."""
    f = geometric_factor(model, positions, target.unsqueeze(1), walls, rects)[..., 0]
    return strength.unsqueeze(1) * f + background.unsqueeze(1)
