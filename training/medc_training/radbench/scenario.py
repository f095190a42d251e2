"""RAD-A2C's search scenarios on a grid: the physics in its units, the SNR bins, and a seeded
generator of episode definitions.

RAD-A2C (Proctor et al., J. Nucl. Eng. 2(4):368-397, 2021) searches for one source in a 20 m x 20 m
area with 0-7 obstructions, on test sets binned by the start's signal-to-noise ratio. This module
states that scenario on 1 m cells (:data:`PHYSICS`, :data:`GRIDS`, :data:`SNR_BINS`) and draws
:class:`Episode` definitions by rejection sampling (:func:`generate_set`). The rules and every
difference from RAD-A2C: docs/radbench.md, "The scenario, and every difference from RAD-A2C".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "BACKGROUND_RANGE",
    "DEFAULT_SEED",
    "GRIDS",
    "LOS_CANDIDATES",
    "MAX_STEPS",
    "MIN_START_M",
    "OBSTRUCTION_COUNTS",
    "OBSTRUCTION_SIDE",
    "PHYSICS",
    "SNR_BINS",
    "SNR_NAMES",
    "STRENGTH_CENTI",
    "SUBBINS",
    "SUCCESS_M",
    "Episode",
    "GenerationStats",
    "GridSpec",
    "generate_set",
    "line_of_sight_blocked",
    "noise_uniforms",
    "snr",
    "snr_bin",
    "start_distance_ok",
    "subbin_edges",
]

#: Source strength in hundredths of counts/s at 1 m, drawn uniformly in [lo, hi): S in [100, 1000).
STRENGTH_CENTI = (10_000, 100_000)
#: Background counts/s, drawn uniformly among the integers lo..hi (both included).
BACKGROUND_RANGE = (10, 50)
#: Obstruction side in cells, lo..hi (both included).
OBSTRUCTION_SIDE = (2, 5)
#: The obstructions' top-left corner lies in the first ceil(CORNER_FRACTION * G) rows and columns.
CORNER_FRACTION = 0.89
#: The obstruction counts of the benchmark (RAD-A2C's test sets: 0-7).
OBSTRUCTION_COUNTS = tuple(range(8))
#: Least distance (metres, cell centre to cell centre) between the source and every start.
MIN_START_M = 10.0
#: Source candidates that must be out of every start's sight before any free one is taken.
LOS_CANDIDATES = 21
#: Moves per episode.
MAX_STEPS = 120
#: A detector within this distance (metres) of the source has found it.
SUCCESS_M = 1.1
#: SNR bins (lo, hi]: the start's (signal + background) / background.
SNR_BINS: dict[str, tuple[float, float]] = {"low": (1.0, 1.2), "medium": (1.2, 1.6), "high": (1.6, 2.0)}
#: The bin names a set may take, in set order; ``none`` puts no condition on the SNR.
SNR_NAMES: tuple[str, ...] = ("low", "medium", "high", "none")
#: Equal-width sub-bins per SNR bin, each a quarter of a set's episodes.
SUBBINS = 4
#: The generator's seed for the frozen sets.
DEFAULT_SEED = 2021
#: What an episode's numbers mean (recorded in every set file).
PHYSICS: dict[str, Any] = {
    "rate": "S / d_m**2 + B counts/s where the line of sight is clear, B where an obstruction blocks it",
    "strength": "S counts/s at 1 m, uniform in [100, 1000) in steps of 0.01",
    "background": "B counts/s, uniform integer in 10..50",
    "counts": "Poisson, 1 s dwell; count-noise stream: see noise_uniforms",
    "success_m": SUCCESS_M,
    "min_start_m": MIN_START_M,
    "max_steps": MAX_STEPS,
    "obstruction_side_cells": list(OBSTRUCTION_SIDE),
    "snr": "(S / d_m**2 + B) / B at each start, line of sight ignored",
    "snr_bins": {name: list(edges) for name, edges in SNR_BINS.items()},
    "subbins": SUBBINS,
}


@dataclass(frozen=True)
class GridSpec:
    """A benchmark area: ``grid`` x ``grid`` cells of ``cell_m`` metres."""

    grid: int
    cell_m: float = 1.0

    @property
    def area_m(self) -> float:
        return self.grid * self.cell_m

    @property
    def corner_cells(self) -> int:
        """Rows (and columns) an obstruction's top-left cell is drawn from."""
        return math.ceil(CORNER_FRACTION * self.grid)

    @property
    def min_start_d2(self) -> int:
        """Least squared distance between the source and a start, in cells²."""
        return math.ceil(MIN_START_M**2 / self.cell_m**2 - 1e-9)


#: The benchmark's areas by grid side.
GRIDS: dict[int, GridSpec] = {20: GridSpec(20, 1.0), 30: GridSpec(30, 1.0)}


def snr(strength: float, background: float, dist2_m: float) -> float:
    """(S / d² + B) / B: the signal-to-noise ratio at squared distance ``dist2_m`` (metres²) from a
    source of strength S (counts/s at 1 m) over a background B (counts/s)."""
    return 1.0 + strength / (background * dist2_m)


def subbin_edges(name: str) -> tuple[float, ...]:
    """The SUBBINS + 1 edges of SNR bin ``name`` (e.g. low: 1.0, 1.05, 1.1, 1.15, 1.2)."""
    lo, hi = SNR_BINS[_check_snr(name, allow_none=False)]
    width = (hi - lo) / SUBBINS
    return (*(round(lo + k * width, 12) for k in range(SUBBINS)), hi)


def snr_bin(value: float) -> str | None:
    """The SNR bin ``value`` falls in ((lo, hi]), or None outside every bin."""
    for name, (lo, hi) in SNR_BINS.items():
        if lo < value <= hi:
            return name
    return None


def _subbin(value: float, edges: tuple[float, ...]) -> int | None:
    for k in range(SUBBINS):
        if edges[k] < value <= edges[k + 1]:
            return k
    return None


def start_distance_ok(starts: Any, source: Any, cell_m: float = 1.0) -> bool:
    """Whether every start (cells (row, col)) is at least :data:`MIN_START_M` metres from the source
    cell, cell centre to cell centre."""
    s = np.asarray(starts, dtype=np.int64).reshape(-1, 2)
    d2 = ((s - np.asarray(source, dtype=np.int64).reshape(1, 2)) ** 2).sum(1)
    return bool((d2 * cell_m**2 >= MIN_START_M**2 - 1e-9).all())


def line_of_sight_blocked(a: Any, b: Any, obstructions: Any) -> bool | np.ndarray:
    """Whether an obstruction stands between cells ``a`` and ``b`` (each (row, col), or arrays [..., 2]
    broadcast together): the open segment between the cell centres passes through the inside of a
    rectangle ``(top, left, bottom, right)`` (inclusive cells, sides half a cell out from the
    centres). A segment that only grazes a corner is clear. The same rule as the environment's
    ``exact`` line of sight (:func:`medc_training.envs.tl_sensing.geometric_factor`)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    rects = np.asarray(obstructions, dtype=np.float64).reshape(-1, 4)
    shape = np.broadcast_shapes(a.shape, b.shape)[:-1]
    if len(rects) == 0:
        out = np.zeros(shape, dtype=bool)
        return bool(out) if out.ndim == 0 else out
    a = np.broadcast_to(a, (*shape, 2))[..., None, :]
    delta = np.broadcast_to(b, (*shape, 2))[..., None, :] - a  # [..., 1, 2]
    lo = rects[:, 0:2] - 0.5  # [Z, 2]
    hi = rects[:, 2:4] + 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / delta
        t0 = (lo - a) * inv
        t1 = (hi - a) * inv
    # Along an axis the segment does not move, it is inside the slab for every t or for none.
    flat = delta == 0.0
    inside = (a > lo) & (a < hi)
    t_min = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    t_max = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    enter = np.maximum(t_min.max(-1), 0.0)
    leave = np.minimum(t_max.min(-1), 1.0)
    out = (enter + 1e-9 < leave).any(-1)
    return bool(out) if out.ndim == 0 else out


def noise_uniforms(seed: int, steps: int, agents: int, run: int = 0) -> np.ndarray:
    """float64 [steps + 1, agents] in (0, 1): the uniform numbers an episode's counts are drawn from,
    reading t (0 = at the start, t = after move t) of agent i at [t, i]: the count is the smallest k
    with PoissonCDF(k; rate) >= u. Made from the raw 64-bit outputs of numpy's PCG64 (a stream numpy
    keeps stable across versions) seeded with ``seed`` for run 0, and with the SeedSequence of
    (seed, run) for another Monte Carlo ``run`` of the same episode: u = ((x >> 11) + 0.5) / 2**53."""
    if isinstance(run, bool) or not isinstance(run, int) or run < 0:
        raise ValueError(f"run must be an integer >= 0, got {run!r}")
    source = int(seed) if run == 0 else np.random.SeedSequence([int(seed), run])
    raw = np.random.PCG64(source).random_raw((steps + 1) * agents)
    return (((raw >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53).reshape(steps + 1, agents)


# ------------------------------------------------------------------------------------------
# episode definitions
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Episode:
    """One benchmark episode: everything that decides it except the policy.

    source:       the source's cell (row, col).
    strength:     S, counts/s at 1 m (the rate is S / d² + B at d metres, line of sight clear).
    background:   B, counts/s.
    starts:       each agent's start cell (row, col), in agent order.
    obstructions: solid rectangles (top row, left column, bottom row, right column), inclusive.
    noise_seed:   the seed of the episode's count-noise stream (:func:`noise_uniforms`).
    """

    source: tuple[int, int]
    strength: float
    background: int
    starts: tuple[tuple[int, int], ...]
    obstructions: tuple[tuple[int, int, int, int], ...]
    noise_seed: int

    def walls(self, grid: int) -> np.ndarray:
        """bool [G, G]: the obstructions' cells."""
        out = np.zeros((grid, grid), dtype=bool)
        for r0, c0, r1, c1 in self.obstructions:
            out[r0:r1 + 1, c0:c1 + 1] = True
        return out

    def dist2_m(self, cell_m: float = 1.0) -> tuple[float, ...]:
        """Each start's squared distance to the source, metres²."""
        sr, sc = self.source
        return tuple(((r - sr) ** 2 + (c - sc) ** 2) * cell_m**2 for r, c in self.starts)

    def snrs(self, cell_m: float = 1.0) -> tuple[float, ...]:
        """Each start's SNR (:func:`snr`)."""
        return tuple(snr(self.strength, self.background, d2) for d2 in self.dist2_m(cell_m))

    def to_json(self) -> dict[str, Any]:
        """The compact JSON form a set file stores (keys: src, S, B, starts, obs, seed)."""
        return {"src": list(self.source), "S": self.strength, "B": self.background,
                "starts": [list(s) for s in self.starts], "obs": [list(o) for o in self.obstructions],
                "seed": self.noise_seed}

    @classmethod
    def from_json(cls, data: Any, grid: int) -> Episode:
        """An episode from :meth:`to_json`'s form, checked against a ``grid`` x ``grid`` area.
        Raises ValueError saying what is wrong."""
        if not isinstance(data, dict) or set(data) != {"src", "S", "B", "starts", "obs", "seed"}:
            raise ValueError("an episode must be an object with exactly the keys src, S, B, starts, obs, "
                             "seed")
        try:
            source = _cell(data["src"], grid)
            starts = tuple(_cell(s, grid) for s in data["starts"])
            obstructions = tuple(_rect(o, grid) for o in data["obs"])
            strength, background, seed = data["S"], data["B"], data["seed"]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"malformed episode: {exc}") from None
        if isinstance(strength, bool) or not isinstance(strength, (int, float)) or not 0 < strength < 1e9:
            raise ValueError(f"episode strength must be a positive number, got {strength!r}")
        if isinstance(background, bool) or not isinstance(background, int) or not 0 < background < 1e9:
            raise ValueError(f"episode background must be a positive integer, got {background!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
            raise ValueError(f"episode seed must be an integer in 0..2**63-1, got {seed!r}")
        if not starts:
            raise ValueError("an episode needs at least one start")
        for i, a in enumerate(obstructions):
            for b in obstructions[i + 1:]:
                if _touch(a, b):
                    raise ValueError(f"obstructions {list(a)} and {list(b)} touch or overlap: the "
                                     "benchmark's layouts keep at least one free cell between two (diagonals "
                                     "included), which its line-of-sight rule relies on; merge them into one "
                                     "or move one")
        return cls(source, float(strength), background, starts, obstructions, seed)


def _cell(value: Any, grid: int) -> tuple[int, int]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < grid for v in value)):
        raise ValueError(f"a cell is [row, col] with integers in 0..{grid - 1}, got {value!r}")
    return int(value[0]), int(value[1])


def _rect(value: Any, grid: int) -> tuple[int, int, int, int]:
    if (not isinstance(value, (list, tuple)) or len(value) != 4
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < grid for v in value)
            or value[0] > value[2] or value[1] > value[3]):
        raise ValueError(f"an obstruction is [top, left, bottom, right] inside the grid, got {value!r}")
    return int(value[0]), int(value[1]), int(value[2]), int(value[3])


# ------------------------------------------------------------------------------------------
# the generator
# ------------------------------------------------------------------------------------------


@dataclass
class GenerationStats:
    """What generating one set took: geometries drawn and kept, and the redraws of each rule."""

    geometries: int = 0
    accepted: int = 0
    obstruction_redraws: int = 0
    disconnected: int = 0
    no_source_cell: int = 0
    source_in_sight: int = 0
    per_subbin: list[int] = field(default_factory=list)

    @property
    def rejection_rate(self) -> float:
        """Share of drawn geometries the SNR condition (or a later rule) discarded."""
        return 1.0 - self.accepted / self.geometries if self.geometries else 0.0

    def to_json(self) -> dict[str, Any]:
        return {"geometries": self.geometries, "accepted": self.accepted,
                "rejection_rate": round(self.rejection_rate, 6),
                "obstruction_redraws": self.obstruction_redraws, "disconnected": self.disconnected,
                "no_source_cell": self.no_source_cell, "source_in_sight": self.source_in_sight,
                "geometries_per_subbin": self.per_subbin}


def _touch(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether two rectangles overlap or touch (no free cell between them, diagonals included)."""
    gap_r = max(b[0] - a[2], a[0] - b[2])
    gap_c = max(b[1] - a[3], a[1] - b[3])
    return max(gap_r, gap_c) <= 1


def _draw_obstructions(rng: np.random.Generator, spec: GridSpec, count: int,
                       stats: GenerationStats) -> list[tuple[int, int, int, int]]:
    lo, hi = OBSTRUCTION_SIDE
    g = spec.grid
    while True:
        placed: list[tuple[int, int, int, int]] = []
        redraws = 0
        while len(placed) < count and redraws < 1000:
            r0, c0 = (int(v) for v in rng.integers(0, spec.corner_cells, size=2))
            h, w = (int(v) for v in rng.integers(lo, hi + 1, size=2))
            rect = (r0, c0, min(r0 + h - 1, g - 1), min(c0 + w - 1, g - 1))
            if any(_touch(rect, p) for p in placed):
                redraws += 1
                stats.obstruction_redraws += 1
                continue
            placed.append(rect)
        if len(placed) == count:
            return placed


def _connected(free: np.ndarray) -> bool:
    """Whether the free cells of ``free`` (bool [G, G]) are one 8-connected region."""
    if not free.any():
        return False
    g = free.shape[0]
    reached = np.zeros((g + 2, g + 2), dtype=bool)
    first = np.argwhere(free)[0]
    reached[first[0] + 1, first[1] + 1] = True
    inner = np.zeros((g + 2, g + 2), dtype=bool)
    inner[1:-1, 1:-1] = free
    count = 1
    while True:
        grown = reached.copy()
        grown[1:, :] |= reached[:-1, :]
        grown[:-1, :] |= reached[1:, :]
        rows = grown.copy()
        rows[:, 1:] |= grown[:, :-1]
        rows[:, :-1] |= grown[:, 1:]
        reached = rows & inner
        now = int(reached.sum())
        if now == count:
            return now == int(free.sum())
        count = now


def _slab(a: float, d: float, inv: float, lo: float, hi: float) -> tuple[float, float]:
    """(t entering, t leaving) of the segment a + t d in the slab lo < x < hi along one axis, with
    ``inv`` = 1 / d (any value when d is 0: the segment is inside for every t or for none)."""
    if d == 0.0:
        return (-math.inf, math.inf) if lo < a < hi else (math.inf, -math.inf)
    t0, t1 = (lo - a) * inv, (hi - a) * inv
    return min(t0, t1), max(t0, t1)


def _hidden_from_all(starts: np.ndarray, source: np.ndarray, rects: list[tuple[int, int, int, int]]) -> bool:
    """``line_of_sight_blocked(starts, source, rects).all()`` for the generator's few starts and
    rectangles, in plain float arithmetic: the same IEEE operations in the same order (a reciprocal,
    then products), hence the same answer, without numpy's per-call cost on arrays of a few
    elements."""
    br, bc = float(source[0]), float(source[1])
    slabs = [(r0 - 0.5, c0 - 0.5, r1 + 0.5, c1 + 0.5) for r0, c0, r1, c1 in rects]
    for start in starts:
        ar, ac = float(start[0]), float(start[1])
        dr, dc = br - ar, bc - ac
        ir = 1.0 / dr if dr != 0.0 else 0.0
        ic = 1.0 / dc if dc != 0.0 else 0.0
        for lo_r, lo_c, hi_r, hi_c in slabs:
            min_r, max_r = _slab(ar, dr, ir, lo_r, hi_r)
            min_c, max_c = _slab(ac, dc, ic, lo_c, hi_c)
            if max(max(min_r, min_c), 0.0) + 1e-9 < min(min(max_r, max_c), 1.0):
                break  # this start's line is blocked
        else:
            return False  # a start sees the source
    return True


def _draw_geometry(rng: np.random.Generator, spec: GridSpec, agents: int, obstructions: int,
                   stats: GenerationStats, cell_rc: np.ndarray):
    """(obstructions, walls, starts int64 [N,2], source int64 [2]) drawn by the rules of the module
    docstring (connectivity is checked by the caller, on the geometries it keeps)."""
    g = spec.grid
    while True:
        rects = _draw_obstructions(rng, spec, obstructions, stats)
        walls = np.zeros((g, g), dtype=bool)
        for r0, c0, r1, c1 in rects:
            walls[r0:r1 + 1, c0:c1 + 1] = True
        free = np.flatnonzero(~walls.ravel())
        starts = cell_rc[rng.choice(free, size=agents, replace=False)]  # [N,2]
        d2 = ((cell_rc[:, None, :] - starts[None, :, :]) ** 2).sum(-1)  # [G²,N]
        allowed = np.flatnonzero((d2 >= spec.min_start_d2).all(1))
        if not (~walls.ravel()[allowed]).any():
            stats.no_source_cell += 1
            continue
        tries = 0
        while True:
            source = cell_rc[allowed[rng.integers(len(allowed))]]
            if walls[source[0], source[1]]:
                tries += 1
                continue
            hidden = obstructions == 0 or _hidden_from_all(starts, source, rects)
            if obstructions and hidden:
                break
            if obstructions == 0 or tries >= LOS_CANDIDATES:
                stats.source_in_sight += int(not hidden)
                break
            tries += 1
        return rects, walls, starts, source


_B_VALUES = np.arange(BACKGROUND_RANGE[0], BACKGROUND_RANGE[1] + 1, dtype=np.int64)


def _pairs_between(x: float, y: float) -> np.ndarray:
    """int64 [len(B values), 2]: per background B, the first and last S (hundredths of counts/s) with
    x < S / B <= y (last < first: none). S / B is the ratio S_counts/s / B."""
    lo_c = np.maximum(np.floor(100.0 * _B_VALUES * x).astype(np.int64) + 1, STRENGTH_CENTI[0])
    hi_c = np.minimum(np.floor(100.0 * _B_VALUES * y).astype(np.int64), STRENGTH_CENTI[1] - 1)
    return np.stack((lo_c, hi_c), 1)


def _count(ranges: np.ndarray) -> int:
    return int(np.maximum(ranges[:, 1] - ranges[:, 0] + 1, 0).sum())


def _ratio_window(d2_m: np.ndarray, name: str, k: int) -> tuple[float, float]:
    """(x, y): the S / B ratios (counts/s over counts/s) that put the team's SNR (its highest, at the
    start nearest the source; squared distances ``d2_m``) in sub-bin ``k`` of bin ``name``:
    x < S / B <= y."""
    edges = subbin_edges(name)
    near = float(d2_m.min())
    return near * (edges[k] - 1.0), near * (edges[k + 1] - 1.0)


def _check_snr(name: str, allow_none: bool = True) -> str:
    names = SNR_NAMES if allow_none else tuple(SNR_BINS)
    if name not in names:
        raise ValueError(f"unknown SNR bin {str(name)[:40]!r}; choose one of {', '.join(names)}")
    return name


def generate_set(grid: int, agents: int, obstructions: int, snr_name: str, episodes: int = 200,
                 seed: int = DEFAULT_SEED) -> tuple[list[Episode], GenerationStats]:
    """``episodes`` episode definitions of one benchmark set, and what drawing them took.

    grid: a key of :data:`GRIDS`; agents: 1..8; obstructions: 0..7; snr_name: one of
    :data:`SNR_NAMES`. With an SNR bin the episodes come a quarter from each sub-bin, interleaved
    (episode i from sub-bin i % 4), so any prefix of 4k episodes is balanced. The same arguments
    give the same episodes (one numpy PCG64 stream seeded from (seed, grid, agents, obstructions,
    bin)). Raises ValueError for arguments out of range.
    """
    if grid not in GRIDS:
        raise ValueError(f"grid must be one of {sorted(GRIDS)}, got {grid!r}")
    for label, value, lo, hi in (("agents", agents, 1, 8), ("obstructions", obstructions, 0, 7),
                                 ("episodes", episodes, 1, 100_000)):
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ValueError(f"{label} must be an integer in {lo}..{hi}, got {value!r}")
    _check_snr(snr_name)
    spec = GRIDS[grid]
    ss = np.random.SeedSequence(int(seed), spawn_key=(grid, agents, obstructions, SNR_NAMES.index(snr_name)))
    rng = np.random.Generator(np.random.PCG64(ss))
    g = spec.grid
    idx = np.arange(g * g)
    cell_rc = np.stack((idx // g, idx % g), 1)
    stats = GenerationStats()
    groups = 1 if snr_name == "none" else SUBBINS
    quota = [episodes // groups + (1 if k < episodes % groups else 0) for k in range(groups)]
    drawn: list[list[Episode]] = []
    for k in range(groups):
        before = stats.geometries
        drawn.append([_draw_episode(rng, spec, agents, obstructions, snr_name, k, stats, cell_rc)
                      for _ in range(quota[k])])
        stats.per_subbin.append(stats.geometries - before)
    out = [drawn[i % groups][i // groups] for i in range(episodes)]
    return out, stats


def _most_pairs(spec: GridSpec, name: str, k: int) -> int:
    """The most (S, B) pairs any one start distance admits into sub-bin ``k`` of bin ``name``."""
    d2 = np.arange(spec.min_start_d2, 2 * (spec.grid - 1) ** 2 + 1) * spec.cell_m**2
    return max(_count(_pairs_between(*_ratio_window(np.array([v]), name, k))) for v in d2)


_MOST: dict[tuple[GridSpec, str, int], int] = {}


def _draw_episode(rng: np.random.Generator, spec: GridSpec, agents: int, obstructions: int, name: str,
                  k: int, stats: GenerationStats, cell_rc: np.ndarray) -> Episode:
    if name != "none":
        key = (spec, name, k)
        if key not in _MOST:
            _MOST[key] = _most_pairs(spec, name, k)
        most = _MOST[key]
        edges = subbin_edges(name)
    while True:
        stats.geometries += 1
        rects, walls, starts, source = _draw_geometry(rng, spec, agents, obstructions, stats, cell_rc)
        d2_m = ((starts - source) ** 2).sum(1).astype(np.float64) * spec.cell_m**2
        if name == "none":
            ranges = np.tile(np.array(STRENGTH_CENTI) - np.array([0, 1]), (len(_B_VALUES), 1))
        else:
            ranges = _pairs_between(*_ratio_window(d2_m, name, k))
            count = _count(ranges)
            if count == 0 or rng.random() * most >= count:
                continue
        if obstructions and not _connected(~walls):
            stats.disconnected += 1
            continue
        weights = np.maximum(ranges[:, 1] - ranges[:, 0] + 1, 0).astype(np.float64)
        for _ in range(100):
            j = int(rng.choice(len(_B_VALUES), p=weights / weights.sum()))
            centi = int(rng.integers(ranges[j, 0], ranges[j, 1] + 1))
            strength, background = centi / 100.0, int(_B_VALUES[j])
            values = [snr(strength, background, float(v)) for v in d2_m]
            if name == "none" or (snr_bin(max(values)) == name and _subbin(max(values), edges) == k):
                break
        else:  # only float rounding at a bin edge can refuse every pair; draw another geometry
            continue
        stats.accepted += 1
        return Episode(source=(int(source[0]), int(source[1])), strength=strength, background=background,
                       starts=tuple((int(r), int(c)) for r, c in starts),
                       obstructions=tuple(rects), noise_seed=int(rng.integers(0, 2**32)))
