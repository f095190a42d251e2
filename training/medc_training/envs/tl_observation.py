"""Target-localization observations: the declared variants, the team's source estimate, the builder.

One pure builder serves the batched core, the PettingZoo env, the experts and the ROS agent
node: each keeps the same team memory (:class:`TeamMemory`: latest normalised reading and visit
count per cell, and the log posterior over source cells) and calls :func:`observe` on it, so a
policy sees in ROS exactly what it saw in training. The variants (:class:`ObservationSpec`:
``maps``, ``egoR``, each with ``+estimate``, ``+posterior`` or both, and ``+information`` after
them), the source estimator's
Poisson posterior (:class:`SourceEstimator`) and the maps drawn from it: docs/environments.md,
"Target-localization observations".
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from contextlib import contextmanager

import torch

from medc_training.envs import tl_native
from medc_training.envs.allocator import keep_freed_memory
from medc_training.envs.grid import action_deltas, grid_cells, team_windows
from medc_training.envs.observation import OBSERVATION_NAMES, ObservationSpec, parse_observation
from medc_training.envs.tl_sensing import (
    CHANNELS,
    DEFAULT_SENSING,
    build_observations,
    crossing_tables,
    geometric_factor,
    parse_sensing,
    rates_from_every_cell,
    sampled_rate_table,
    segment_crossings,
    sight_lines,
    update_memory,
    visit_norm,
    wall_rectangles,
    wall_segments,
)

__all__ = [
    "DEFAULT_OBSERVATION",
    "EGO_CHANNELS",
    "ESTIMATE_CHANNEL",
    "INFORMATION_CHANNEL",
    "LOG_FLOOR",
    "MAP_CHANNELS",
    "OBSERVATION_NAMES",
    "POSTERIOR_CHANNEL",
    "ObservationSpec",
    "SourceEstimator",
    "TeamMemory",
    "observation_channels",
    "observation_shape",
    "observe",
    "observe_agent",
    "parse_observation",
]

#: The observation a target-localization environment produces unless told otherwise. Chosen by
#: measurement (docs/environments.md, "Observations").
DEFAULT_OBSERVATION = "ego6+estimate"
#: The absolute maps (the paper's 5).
MAP_CHANNELS: tuple[str, ...] = CHANNELS
#: The agent-centred window.
EGO_CHANNELS: tuple[str, ...] = ("walls", "team_locations", "readings", "visit_counts")
#: Last when the view shows the team's source estimate (before the posterior when it shows both).
ESTIMATE_CHANNEL = "source_estimate"
#: After the estimate when the view shows the team's source posterior.
POSTERIOR_CHANNEL = "source_posterior"
#: Last when the view shows the information a reading would bring where the team can stand next.
INFORMATION_CHANNEL = "source_information"
#: Relative log-probability floor of the source posterior (exp(-104) underflows float32 to 0).
LOG_FLOOR = -104.0
#: Below this relative log probability a cell's weight is taken as 0 (exp(-87) is about float32's
#: smallest normal number).
EXP_FLOOR = -87.0
#: Largest reading the estimator takes (counts/s): 1000x the model's highest rate, S + BG = 1001.
MAX_READING = 1e6
#: A posterior over levels is updated and marginalised a block of episodes at a time, of about this
#: many bytes of float32 [episodes, levels, G²]: a block stays in a core's L2 cache through the
#: pass's element-wise steps (add, floor, max, shift, clamp; floor, exp, sum), where the whole batch
#: (20 MB at B = 256, 48 levels, 20×20) would stream through L3 once per step. Every episode's
#: arithmetic is the same either way.
BLOCK_BYTES = 1 << 20
#: The estimator's two implementations of the same posterior (:data:`ESTIMATOR_PATH`).
ESTIMATOR_PATHS = ("fused", "reference")
#: Which implementation new estimators take: ``fused`` (the default) keeps a posterior over levels
#: cells-major and folds a step's readings, the renormalisation and the marginal over the levels into
#: one pass per block of episodes; ``reference`` is the level-major implementation it replaced, kept
#: so that ``medc-bench env`` and ``medc-bench train`` measure both in one run. The two agree within
#: rounding (docs/environments.md, "Speed"). ``MEDC_ESTIMATOR=reference`` in the environment selects
#: the reference for a whole process; :func:`estimator_path` for the estimators made inside a block.
ESTIMATOR_PATH = os.environ.get("MEDC_ESTIMATOR", "fused")
if ESTIMATOR_PATH not in ESTIMATOR_PATHS:
    raise ValueError(f"MEDC_ESTIMATOR must be one of {ESTIMATOR_PATHS}, got {ESTIMATOR_PATH[:40]!r}")
_LOG2E = 1.0 / math.log(2.0)


def observation_channels(observation) -> tuple[str, ...]:
    """The channel names of view ``observation`` (a name or spec), in order."""
    spec = parse_observation(observation)
    base = MAP_CHANNELS if spec.view == "maps" else EGO_CHANNELS
    return (base + ((ESTIMATE_CHANNEL,) if spec.estimate else ())
            + ((POSTERIOR_CHANNEL,) if spec.posterior else ())
            + ((INFORMATION_CHANNEL,) if spec.information else ()))


def observation_shape(observation, grid: int) -> tuple[int, int, int]:
    """(C, H, W) of one agent's view ``observation`` (a name or spec) on a ``grid``×``grid`` area."""
    spec = parse_observation(observation)
    return spec.shape(grid, len(observation_channels(spec)))


@contextmanager
def estimator_path(path: str):
    """Make the estimators (and team memories) created inside the block take ``path`` (one of
    :data:`ESTIMATOR_PATHS`)."""
    global ESTIMATOR_PATH
    if path not in ESTIMATOR_PATHS:
        raise ValueError(f"estimator path must be one of {ESTIMATOR_PATHS}, got {path!r}")
    before, ESTIMATOR_PATH = ESTIMATOR_PATH, path
    try:
        yield
    finally:
        ESTIMATOR_PATH = before


class _FusedLevels:
    """The fused path's steps over a cells-major posterior over levels (:class:`SourceEstimator`)."""

    grid: int
    levels: int

    def cells_major(self, log_post: torch.Tensor) -> bool:
        """Whether ``log_post`` [K, L, G²] is a view of cells-major memory [K, G², L] (the fused
        path's layout, :meth:`prior`)."""
        return (log_post.dim() == 3 and log_post.shape[1] > 1 and log_post.stride(1) == 1
                and log_post.stride(2) == log_post.shape[1])

    def _fused_update(self, log_post: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor,
                      readings: torch.Tensor, d2: torch.Tensor, crossed: torch.Tensor,
                      posterior_out: torch.Tensor | None) -> None:
        """:meth:`update` of a cells-major posterior over levels from per-(d², walls crossed) tables.

        A block of episodes at a time (:data:`BLOCK_BYTES`), every step over contiguous memory while
        the block is in cache: one ``embedding_bag`` makes each (episode, cell)'s row of L
        log-likelihoods, sum_n r_n log rate_n - S sum_n factor_n - N B (the reference's arithmetic, in
        its order), from N + 2 table rows (the N readings' log-rate rows weighted by the readings, the
        strength row by -sum_n factor_n, the background row by -N); it is added to the posterior,
        the ruled-out cells are floored, the block is shifted by its episodes' maxima and floored, and
        (``posterior_out``) the marginal over the levels is summed from exp2 of the block scaled by
        log2(e) (float32's exp2 is about 3x faster than its exp here)."""
        k, n = readings.shape
        cells, levels = self.grid * self.grid, self.levels
        span = self._span  # d² takes the values 0 .. span - 1
        table = self._levels_table(int(crossed.max()) if crossed.numel() else 0)
        q_rows = table.shape[0] - 2
        out = self._ruled_out_cells(walls, positions)
        phys = log_post.transpose(1, 2)  # [K,G²,L], contiguous per episode
        # Each (episode, cell)'s bag: the readings' log-rate rows weighted by the readings, the strength
        # row weighted by -sum_n factor_n, the background row by -N.
        index = torch.add(d2, crossed, alpha=span)  # [K,N,G²]
        bags = torch.empty((k, cells, n + 2), dtype=torch.int64, device=self.device)
        bags[..., :n] = index.transpose(1, 2)
        bags[..., n] = q_rows
        bags[..., n + 1] = q_rows + 1
        weights = torch.empty((k, cells, n + 2), device=self.device)
        weights[..., :n] = readings.unsqueeze(1)
        torch.sum(self._bag_factor.index_select(0, index.view(-1)).view(k, n, cells), 1, out=weights[..., n])
        weights[..., n].neg_()
        weights[..., n + 1] = -float(n)
        bags, weights = bags.view(k * cells, n + 2), weights.view(k * cells, n + 2)
        episode, cell = out.nonzero(as_tuple=True)  # in episode order
        step = self.block(k)
        starts = list(range(0, k, step))
        cuts = torch.searchsorted(episode, torch.tensor([*starts, k], device=episode.device)).tolist()
        for i, s in enumerate(starts):
            e = min(k, s + step)
            kb = e - s
            loglik = torch.nn.functional.embedding_bag(bags[s * cells:e * cells], table, mode="sum",
                                                       per_sample_weights=weights[s * cells:e * cells])
            block = phys[s:e]
            block.add_(loglik.view(kb, cells, levels))
            lo, hi = cuts[i], cuts[i + 1]
            if hi > lo:
                block[episode[lo:hi] - s, cell[lo:hi]] = LOG_FLOOR
            block.sub_(block.amax((1, 2), keepdim=True)).clamp_(min=LOG_FLOOR)
            if posterior_out is not None:
                self._marginal(block, loglik.view(kb, cells, levels), posterior_out[s:e])
        if posterior_out is not None:
            self._normalise(posterior_out)

    def _levels_table(self, most: int) -> torch.Tensor:
        """The fused path's [Q + 2, L] table for up to ``most`` walls crossed: log rates per (d², walls
        crossed) pair q = d² + span * crossed, then the levels' strengths and backgrounds; also keeps
        the pairs' geometric factors [Q] (``_bag_factor``)."""
        span, table = self._span, self._bag_table
        if table is None or table.shape[0] < span * (most + 1) + 2:
            log_rate, factor = _rate_tables(self.sensing, self.level_strength, self.level_background, span,
                                            most, self.device)
            levels_s, levels_b = self.level_strength.view(1, -1), self.level_background.view(1, -1)
            table = self._bag_table = torch.cat((log_rate, levels_s, levels_b)).contiguous()  # [Q+2, L]
            self._bag_factor = factor  # [Q]
        return table

    def _ruled_out_cells(self, walls: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """bool [K, G²]: walls, and (``rule_out``) the cells an agent stands within reach of."""
        out = walls.reshape(walls.shape[0], -1).bool()
        return out | self.ruled_out(positions) if self.rule_out else out

    def _native_levels(self, log_post: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor,
                       readings: torch.Tensor, rects: torch.Tensor | None,
                       posterior_out: torch.Tensor | None) -> bool:
        """:meth:`update` of a cells-major posterior over levels under the exact line rule in one C pass
        per episode (``tl_native.c``: the line of sight, the log-likelihood rows, the shift and the
        marginal), when the kernel is there; returns whether it ran."""
        phys = log_post.transpose(1, 2)  # [K,G²,L]
        if rects is None:
            rects = wall_rectangles(walls)
        positions, rects = positions.contiguous(), rects.to(torch.float32).contiguous()
        if not tl_native.usable(phys, positions, rects):
            return False
        count = self.sensing.attenuation > 0.0
        table = self._levels_table(rects.shape[1] if count else 1)
        q_rows = table.shape[0] - 2
        tl_native.levels_update(phys, table[:q_rows], self._bag_factor, self.level_strength,
                                self.level_background, positions, rects, count, self._span,
                                readings.to(torch.float32).contiguous(),
                                self._ruled_out_cells(walls, positions).contiguous(), posterior_out,
                                self._dead_cell)
        return True

    def _marginal(self, block: torch.Tensor, scratch: torch.Tensor, out: torch.Tensor) -> None:
        """Sum over the levels of exp(``block``) (cells-major [k, G², L]) into ``out`` [k, G²], through
        ``scratch`` (same shape, contiguous); entries at or below EXP_FLOOR weigh exp(EXP_FLOOR)."""
        weights = torch.clamp(block, min=EXP_FLOOR, out=scratch).mul_(_LOG2E).exp2_()
        torch.sum(weights, 2, out=out)

    def _normalise(self, p: torch.Tensor) -> torch.Tensor:
        """``p`` [K, G²] of :meth:`_marginal`, in place: dead cells exactly 0, rows summing to 1."""
        p.masked_fill_(p <= self._dead_cell, 0.0)
        return p.div_(p.sum(1, keepdim=True))


def _rate_tables(sensing, strength: torch.Tensor, background: torch.Tensor, span: int, most: int,
                 device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(log rate float32 [Q, L], geometric factor float32 [Q]) for every pair q = d² + span * crossed
    with up to ``most`` (at least 1) walls crossed: rate = S * A**crossed / (1 + d²) + B per level."""
    q = torch.arange(span * (max(most, 1) + 1), device=device)
    crossings, dist2 = (q // span).to(torch.float32), (q % span).to(torch.float32)
    factor = sensing.attenuation ** crossings / (1.0 + dist2)
    rate = factor * strength.view(-1, 1) + background.view(-1, 1)  # [L,Q]
    return rate.log().t(), factor


class _ReadingTables:
    """The reference path's log-likelihood of readings from per-(d², walls crossed) tables of log
    rates, made on first use and grown with the most walls crossed."""

    def __init__(self, grid: int, sensing, level_strength: torch.Tensor, level_background: torch.Tensor,
                 device: torch.device) -> None:
        self.grid, self.sensing, self.device = grid, sensing, device
        self.level_strength, self.level_background = level_strength, level_background
        self.levels = level_strength.shape[0]
        #: (log rate [Q, L], factor [Q]) for Q = (d², walls crossed) pairs.
        self._tables: tuple[torch.Tensor, torch.Tensor] | None = None

    def loglik(self, d2: torch.Tensor, crossed: torch.Tensor, readings: torch.Tensor) -> torch.Tensor:
        """float32 [K,L,G²] (or [K,G²] with one level): sum over the readings of r log(rate) - rate,
        with rate = S * A**k / (1 + d²) + B looked up in per-(d², k) tables (no log per reading).
        The log rates of one (d², k) pair are one contiguous row of L; each (episode, cell) sums its
        readings' rows weighted by the readings in one ``embedding_bag`` (reading by reading, element
        by element: no BLAS, whose blocking would make an episode's sum depend on the batch size).
        Returned as a [K,L,G²] view of [K,G²,L] memory."""
        k, n = readings.shape
        span = 2 * (self.grid - 1) ** 2 + 1  # d² takes the values 0 .. span - 1
        most = int(crossed.max()) if crossed.numel() else 0
        if self._tables is None or self._tables[0].shape[0] < span * (most + 1):
            log_rate, factor = _rate_tables(self.sensing, self.level_strength, self.level_background, span,
                                            most, self.device)
            self._tables = (log_rate.contiguous(), factor)
        log_rate, factor = self._tables
        index = d2 + span * crossed  # [K,N,G²]
        cells = d2.shape[-1]
        # Per (episode, cell), the sum over the readings of r * log rate row: one weighted bag of N
        # table rows each (embedding_bag sums a bag's rows in order, r_0 * row_0 + r_1 * row_1 + ...,
        # the arithmetic of a product and then one multiply-add per reading, in one pass).
        bags = index.transpose(1, 2).reshape(k * cells, n)
        weights = readings.view(k, 1, n).expand(k, cells, n).reshape(k * cells, n)
        loglik = torch.nn.functional.embedding_bag(bags, log_rate, mode="sum",
                                                   per_sample_weights=weights).view(k, cells, self.levels)
        fsum = factor.index_select(0, index.view(-1)).view(k, n, -1).sum(1)  # [K,G²]
        loglik.sub_(fsum.unsqueeze(-1) * self.level_strength).sub_(n * self.level_background)
        loglik = loglik.transpose(1, 2)
        return loglik if self.levels > 1 else loglik.squeeze(1)


def _factor_loglik(f: torch.Tensor, readings: torch.Tensor, strength: torch.Tensor,
                   background: torch.Tensor) -> torch.Tensor:
    """float32 [K, L, G²]: the readings' log-likelihood sum_n r_n log(S f_n + B) - S sum_n f_n - n B
    of every level (strength S, background B) and cell, from the geometric factors ``f`` [K,N,G²]."""
    k, n = f.shape[:2]
    strength, background = strength.view(-1, 1), background.view(-1, 1)
    rate = torch.addcmul(background, f.unsqueeze(2), strength)  # [K,N,L,G²]: one log per reading, level, cell
    loglik = rate.log_().mul_(readings.view(k, n, 1, 1)).sum(1)  # [K,L,G²]
    return loglik.sub_(f.sum(1).unsqueeze(1) * strength).sub_(n * background)


def _fold(log_post: torch.Tensor, out: torch.Tensor, levels: int, block: Callable[[int], int],
          loglik: torch.Tensor | None, block_loglik: Callable[[int, int], torch.Tensor] | None) -> None:
    """Add the readings' log-likelihood to ``log_post`` in place, write LOG_FLOOR on the ``out``
    cells (bool [K, G²]: walls, ruled out) and shift each episode's maximum to 0, clamped at
    LOG_FLOOR. Over ``levels`` > 1 it goes ``block(K)`` episodes at a time while they are in cache,
    ``block_loglik(s, e)`` (else ``loglik``) giving episodes s..e's log-likelihood."""
    k = log_post.shape[0]
    # The few ruled-out cells are written by index: a mask broadcast over every level would
    # pass over the whole [K, L, G²] posterior.
    episode, cell = out.nonzero(as_tuple=True)  # in episode order
    if levels == 1:
        log_post.add_(loglik)
        flat = log_post.view(k, 1, -1)
        flat[episode, :, cell] = LOG_FLOOR
        flat.sub_(flat.amax((1, 2), keepdim=True)).clamp_(min=LOG_FLOOR)
        return
    if block_loglik is None:
        def block_loglik(s: int, e: int) -> torch.Tensor:
            return loglik[s:e]
    step = block(k)
    starts = list(range(0, k, step))
    cuts = torch.searchsorted(episode, torch.tensor([*starts, k], device=episode.device)).tolist()
    for i, s in enumerate(starts):
        e = min(k, s + step)
        part = log_post[s:e]
        part.add_(block_loglik(s, e))
        lo, hi = cuts[i], cuts[i + 1]
        if hi > lo:
            part[episode[lo:hi] - s, :, cell[lo:hi]] = LOG_FLOOR
        part.sub_(part.amax((1, 2), keepdim=True)).clamp_(min=LOG_FLOOR)


def _levels_marginal(log_post: torch.Tensor, step: int) -> torch.Tensor:
    """float32 [K, G²]: the sum over the levels of a levels-major log posterior [K, L, G²]
    (unnormalised; weights at or below EXP_FLOOR exactly 0), ``step`` episodes at a time."""
    # Only the (episode, level) rows with a cell above the floor are exponentiated (after a
    # few readings about half of them have none); the others stay exact zeros, and the sum
    # over the levels runs as over the whole tensor (the same rounding).
    k, levels, cells = log_post.shape
    p = torch.empty((k, cells), device=log_post.device)
    for s in range(0, k, step):
        rows = log_post[s:s + step].reshape(-1, cells)
        alive = (rows.amax(1) > EXP_FLOOR).nonzero().squeeze(1)
        weights = rows.index_select(0, alive)
        dead = weights <= EXP_FLOOR
        weights.clamp_(min=EXP_FLOOR).exp_().masked_fill_(dead, 0.0)
        dense = torch.zeros_like(rows).index_copy_(0, alive, weights).view(-1, levels, cells)
        torch.sum(dense, 1, out=p[s:s + step])
    return p


class SourceEstimator(_FusedLevels):
    """The team's Bayes posterior over the source cell on a ``grid``×``grid`` area (module docstring).

    Stateless apart from per-grid constants; the posterior lives in a ``log_post`` tensor the caller
    owns (:class:`TeamMemory`): float32 [B, G*G] when the sensing model's strength and background
    are known, else [B, L, G*G] over (strength-and-background level, source cell), L = ns * nb
    levels, strength-major (:class:`~medc_training.envs.tl_sensing.SensingModel`).
    """

    def __init__(self, grid: int, device: torch.device | str, sensing=DEFAULT_SENSING,
                 rule_out: bool = True, path: str | None = None) -> None:
        """``rule_out``: a cell some agent has stood within the success radius of is not the source
        (true when an episode ends as soon as an agent finds the source, as in training); False for
        episodes that a finding does not end (a driver that ends them on the team's declaration).
        ``path``: one of :data:`ESTIMATOR_PATHS` (None: :data:`ESTIMATOR_PATH`)."""
        self.path = ESTIMATOR_PATH if path is None else path
        if self.path not in ESTIMATOR_PATHS:
            raise ValueError(f"estimator path must be one of {ESTIMATOR_PATHS}, got {self.path!r}")
        self.grid = int(grid)
        self.rule_out = bool(rule_out)
        self.device = torch.device(device)
        self.sensing = parse_sensing(sensing)
        g = self.grid
        self.cells = grid_cells(g, self.device)  # [G²,2] (row, col)
        self.scale = 1.0 / max(1, g - 1)
        # Diagonal coordinates of every cell and |i - j| between diagonals, for expected_moves.
        self._u = self.cells[:, 0] + self.cells[:, 1]
        self._v = self.cells[:, 0] - self.cells[:, 1] + (g - 1)
        lines = torch.arange(2 * g - 1, device=self.device, dtype=torch.float32)
        self._gap = (lines.unsqueeze(1) - lines.unsqueeze(0)).abs()
        self.levels = self.sensing.levels[0] * self.sensing.levels[1]
        #: [K] strength and background of each level, strength-major.
        self.level_strength, self.level_background = self.sensing.level_values(self.device)
        self._reading_tables = _ReadingTables(g, self.sensing, self.level_strength, self.level_background,
                                              self.device)
        #: The paper-simple model's (rate, log rate) by (walls crossed, d²), made on first use.
        self._sampled: tuple[torch.Tensor, torch.Tensor] | None = None
        self._span = 2 * (g - 1) ** 2 + 1
        lines = torch.arange(g, device=self.device)
        self._square = ((lines.unsqueeze(1) - lines.unsqueeze(0)) ** 2).int()  # int32 [G, G]: (i - j)²
        #: int64 [O,2]: the (row, column) offsets within the success radius, made on first use.
        self._reach: torch.Tensor | None = None
        #: The fused path's [Q + 2, L] table (log rates per (d², walls crossed) pair, then the levels'
        #: strengths and backgrounds) and [Q] geometric factors.
        self._bag_table: torch.Tensor | None = None
        self._bag_factor: torch.Tensor | None = None
        #: A cell whose weights summed over the levels are at most this gets exactly 0 from the fused
        #: path: every level of it is at or below EXP_FLOOR. (The reference writes each such weight as
        #: 0; the fused path takes exp(EXP_FLOOR) for them, which keeps its exp off float32's slow
        #: subnormal path, and then clears the cell.)
        self._dead_cell = 1.0001 * self.levels * math.exp(EXP_FLOOR)

    @property
    def fused(self) -> bool:
        """Whether this estimator keeps a posterior over levels cells-major and takes the fused path."""
        return self.path == "fused" and self.levels > 1

    def prior(self, walls: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²] (or [K, levels, G²]) log prior: 0 on free cells, LOG_FLOOR on walls."""
        k = walls.shape[0]
        if self.fused:  # [K, L, G²] seen through cells-major memory [K, G², L]
            prior = torch.zeros((k, self.grid * self.grid, self.levels), device=self.device).transpose(1, 2)
        else:
            prior = torch.zeros((k, self.levels, self.grid * self.grid), device=self.device)
        prior.masked_fill_(walls.reshape(k, 1, -1).bool(), LOG_FLOOR)
        return prior if self.levels > 1 else prior.squeeze(1)

    def update(self, log_post: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor,
               readings: torch.Tensor, rects: torch.Tensor | None = None,
               segments: torch.Tensor | None = None, posterior_out: torch.Tensor | None = None) -> bool:
        """Fold the team's readings at ``positions`` (int64 [K,N,2]) into ``log_post`` in place.

        walls bool [K,G,G]; readings float32 [K,N] (counts/s, as the sensor returns them); ``rects``
        the episode's wall rectangles (:func:`~medc_training.envs.tl_sensing.wall_rectangles`; made
        from ``walls`` when not given) for the exact line-of-sight rule; ``segments`` the walls as
        :func:`~medc_training.envs.tl_sensing.wall_segments` gives them, when every map is made of
        segments, for the sampled rule's crossing tables. Cost: O(G² · levels) per reading (plus
        O(G² · walls) for the line of sight; O(G³) per reading for the sampled rule without
        ``segments``).

        ``posterior_out`` float32 [K, G²]: on the fused path the updated posterior (:meth:`posterior`)
        is also written there, each block while it is in cache; returns whether it was.
        """
        k = positions.shape[0]
        # No sensor of this model reads more than MAX_READING; a larger (or infinite) value from a
        # mismatched or faulty sensor is taken as MAX_READING, so the float32 sums below stay finite.
        readings = torch.nan_to_num(readings, nan=0.0, posinf=MAX_READING).clamp(0.0, MAX_READING)
        crossed = None
        loglik = None  # float32 [K,G²] or [K,L,G²]; or made block by block by `block_loglik`
        block_loglik = None
        if (self.sensing.line == "sampled" and segments is not None and self.levels == 1
                and self.path == "fused"
                and self._native_single(log_post, walls, positions, readings, segments, posterior_out)):
            return posterior_out is not None
        if self.sensing.line == "sampled" and segments is not None:
            crossed = segment_crossings(positions, segments, self.grid)  # [K,N,G²] or None
        if crossed is not None and self.levels == 1:
            # The sensor model's rate and its log, looked up by (walls crossed, d²).
            most = max(1, segments.shape[1])
            if self._sampled is None or self._sampled[0].shape[0] < (most + 1) * self._span:
                self._sampled = sampled_rate_table(self.grid, most, self.device)
            index = crossed.mul_(self._span).add_(self.dist2(positions))
            flat = index.view(-1)
            rate = self._sampled[0].index_select(0, flat).view_as(index)
            logs = self._sampled[1].index_select(0, flat).view_as(index)
            loglik = logs.mul_(readings.unsqueeze(-1)).sub_(rate).sum(1)  # [K,G²]
        elif self.sensing.line == "sampled" and self.levels == 1:
            rate = rates_from_every_cell(positions, walls)  # [K,N,G²]: the simulator's sensor model
            loglik = (readings.unsqueeze(-1) * torch.log(rate) - rate).sum(1)  # [K,G²]
        elif (self.sensing.line == "exact" and self.levels > 1 and self.path == "fused"
              and self.cells_major(log_post)
              and self._native_levels(log_post, walls, positions, readings, rects, posterior_out)):
            return posterior_out is not None
        elif (lines := self._sight_lines(positions, walls, rects)) is not None:
            d2, crossed = lines
            if self.levels > 1 and self.path == "fused" and self.cells_major(log_post):
                self._fused_update(log_post, walls, positions, readings, d2, crossed, posterior_out)
                return posterior_out is not None
            if self.levels == 1:
                loglik = self._reading_tables.loglik(d2, crossed, readings)
            else:
                def block_loglik(s: int, e: int) -> torch.Tensor:
                    return self._reading_tables.loglik(d2[s:e], crossed[s:e], readings[s:e])
        else:
            loglik = _factor_loglik(geometric_factor(self.sensing, positions, self.cells, walls, rects),
                                    readings, self.level_strength, self.level_background)
            if self.levels == 1:
                loglik = loglik.squeeze(1)
        # Standing within reach of a cell without the episode ending rules it out as the source.
        out = walls.reshape(k, -1).bool()
        if self.rule_out:
            out = out | self.ruled_out(positions)
        _fold(log_post, out, self.levels, self.block, loglik, block_loglik)
        return False

    def _native_single(self, log_post: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor,
                       readings: torch.Tensor, segments: torch.Tensor,
                       posterior_out: torch.Tensor | None) -> bool:
        """:meth:`update` of a one-level posterior under the sampled rule in one C pass per episode
        (``tl_native.c``: the crossings, the rate lookups, the shift and the posterior), when the kernel
        and the grid's crossing tables are there; returns whether it ran."""
        table = crossing_tables(self.grid, self.device)
        positions, segments = positions.contiguous(), segments.contiguous()
        if table is None or not tl_native.usable(log_post, positions, segments):
            return False
        most = max(1, segments.shape[1])
        if self._sampled is None or self._sampled[0].shape[0] < (most + 1) * self._span:
            self._sampled = sampled_rate_table(self.grid, most, self.device)
        out = self._ruled_out_cells(walls, positions)
        tl_native.single_update(log_post, self._sampled[0], self._sampled[1], self._span, positions, table,
                                segments, readings.to(torch.float32).contiguous(), out.contiguous(),
                                posterior_out)
        return True

    def block(self, k: int) -> int:
        """Episodes per block of a posterior over levels (:data:`BLOCK_BYTES`), for a batch of ``k``."""
        return max(1, min(k, BLOCK_BYTES // (4 * self.levels * self.grid * self.grid)))

    def _sight_lines(self, positions: torch.Tensor, walls: torch.Tensor,
                     rects: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor] | None:
        if self.sensing.line != "exact":
            return None
        if rects is None:
            rects = wall_rectangles(walls)
        return sight_lines(self.sensing, positions, walls, rects, fused=self.path == "fused")

    def ruled_out(self, positions: torch.Tensor) -> torch.Tensor:
        """bool [K, G²]: the cells an agent stands within ``success_radius`` of (the source would
        have ended the episode there), marked from the few offsets within reach of each agent."""
        k, g = positions.shape[0], self.grid
        if self._reach is None:
            r = math.floor(self.sensing.success_radius)
            offsets = torch.tensor([(dr, dc) for dr in range(-r, r + 1) for dc in range(-r, r + 1)],
                                   device=self.device)
            self._reach = offsets[self.sensing.within_reach((offsets * offsets).sum(1))]  # [O,2]
        cells = positions.unsqueeze(2) + self._reach  # [K,N,O,2]
        inside = ((cells >= 0) & (cells < g)).all(-1)
        episode = torch.arange(k, device=self.device).view(k, 1, 1).expand_as(inside)
        out = torch.zeros((k, g * g), dtype=torch.bool, device=self.device)
        out[episode[inside], (cells[..., 0] * g + cells[..., 1])[inside]] = True
        return out

    def dist2(self, positions: torch.Tensor) -> torch.Tensor:
        """int32 [K,N,G²]: d² (cells²) from each of ``positions`` (int64 [K,N,2]) to every cell, from
        two O(G²) tables of squared row and column gaps."""
        k, n = positions.shape[:2]
        rows = self._square.index_select(0, positions[..., 0].reshape(-1)).view(k, n, self.grid, 1)
        cols = self._square.index_select(0, positions[..., 1].reshape(-1)).view(k, n, 1, self.grid)
        return (rows + cols).view(k, n, -1)

    def posterior(self, log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²] posterior probabilities of the source cell (strength and background
        marginalised). Cells below :data:`EXP_FLOOR` get exactly 0: their weight is below float32's
        smallest normal number (no denormals, which are slow) and could not move a sum that holds
        the most probable cell's 1."""
        # Entries at or below the floor are written as exact zeros after an exp of the floor itself:
        # exp(-inf), and exp near float32's underflow, take a slow path (3-30x a plain exp).
        if log_post.dim() == 2 and self.path == "fused" and tl_native.usable(log_post):
            return tl_native.single_posterior(log_post)  # as the one-level kernel's update writes it
        if log_post.dim() == 2:
            p = log_post.clamp(min=EXP_FLOOR).exp_().masked_fill_(log_post <= EXP_FLOOR, 0.0)
        elif self.path == "fused" and self.cells_major(log_post):
            k, levels, cells = log_post.shape
            phys = log_post.transpose(1, 2)
            p = torch.empty((k, cells), device=log_post.device)
            if tl_native.usable(phys):
                tl_native.levels_marginal(phys, p, self._dead_cell)
                return p
            step = self.block(k)
            scratch = torch.empty((min(k, step), cells, levels), device=log_post.device)
            for s in range(0, k, step):
                e = min(k, s + step)
                self._marginal(phys[s:e], scratch[:e - s], p[s:e])
            return self._normalise(p)
        else:
            p = _levels_marginal(log_post, self.block(log_post.shape[0]))
        return p / p.sum(1, keepdim=True)

    def expected_moves(self, log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²]: E(c), the posterior-expected Chebyshev distance to the source.

        O(G²) per map: max(|dr|, |dc|) = (|u_c - u_s| + |v_c - v_s|) / 2 with u = row + col and
        v = row - col, so E(c) = (A_u(u_c) + A_v(v_c)) / 2 where A_u(x) = sum_u P_u(u) |x - u| over
        the posterior's marginal P_u on each diagonal (2G - 1 values), and likewise for v. Each
        episode's arithmetic is its own (a broadcast product, not a matrix product that BLAS would
        block by batch size), so one episode's estimate never depends on how many share its batch.
        """
        return self.expected_from_posterior(self.posterior(log_post))

    def expected_from_posterior(self, p: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²]: :meth:`expected_moves` of a posterior float32 [K, G²] (rows summing to 1)."""
        k, g = p.shape[0], self.grid
        if self.path == "fused" and p.dtype == torch.float32 and tl_native.usable(p):
            return tl_native.expected_moves(p, g)
        diagonals = 2 * g - 1
        marginal_u = torch.zeros((k, diagonals), device=p.device).index_add_(1, self._u, p)
        marginal_v = torch.zeros((k, diagonals), device=p.device).index_add_(1, self._v, p)
        spread_u = (marginal_u.unsqueeze(1) * self._gap).sum(-1)  # [K, 2G-1]
        spread_v = (marginal_v.unsqueeze(1) * self._gap).sum(-1)
        return 0.5 * (spread_u[:, self._u] + spread_v[:, self._v])

    def estimate_map(self, log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G, G]: 1 - E(c)/(G-1), the map the observations show."""
        k = log_post.shape[0]
        e = (1.0 - self.expected_moves(log_post) * self.scale).clamp_(0.0, 1.0)
        return e.view(k, self.grid, self.grid)


class TeamMemory:
    """What a team knows in B episodes at once: the memory the observations are built from.

    ``reading_map`` float32 [B,G,G] (latest normalised reading per cell, 0 = never visited),
    ``visit_map`` float32 [B,G,G] (raw visit counts), ``log_post`` (the source posterior,
    :class:`SourceEstimator`; kept when the observation shows the estimate or the posterior, or
    ``posterior`` is True), ``rects`` float32 [B,Z,4] (each episode's wall rectangles, for the exact
    line-of-sight rule). The batched core, the PettingZoo env and the ROS agent node hold one each and
    feed it the same readings, under the same ``sensing`` model. ``rule_out``, ``path``:
    :class:`SourceEstimator`'s.

    A posterior over levels is, on the fused path, a [B, L, G²] view of cells-major memory; readers
    index it as [B, L, G²] either way. The fused path also keeps the marginal posterior it made with
    the last update (:meth:`posterior`), while ``log_post`` is unchanged since.
    """

    def __init__(self, spec: ObservationSpec, batch: int, grid: int, device: torch.device | str,
                 sensing=DEFAULT_SENSING, posterior: bool = False, max_walls: int = 1,
                 rule_out: bool = True, path: str | None = None) -> None:
        self.spec = parse_observation(spec)
        self.sensing = parse_sensing(sensing)
        self.grid = int(grid)
        self.device = torch.device(device)
        self.max_walls = max(1, int(max_walls))
        g = self.grid
        self.reading_map = torch.zeros((batch, g, g), device=self.device)
        self.visit_map = torch.zeros((batch, g, g), device=self.device)
        keep = self.spec.source_views or posterior
        self.estimator = SourceEstimator(g, self.device, self.sensing, rule_out, path) if keep else None
        #: The fused path's marginal posterior [B, G²] of ``log_post`` as it was at (data pointer,
        #: version) ``_post_key``.
        self._post: torch.Tensor | None = None
        self._post_key: tuple[int, int] | None = None
        if keep and self.estimator.levels > 1 and self.device.type == "cpu":
            keep_freed_memory()  # its per-step temporaries are B x G² x levels floats
        blank = torch.zeros((batch, g, g), dtype=torch.bool, device=self.device)
        self.log_post = self.estimator.prior(blank) if keep else None
        blank = torch.zeros((batch, g, g), dtype=torch.bool, device=self.device)
        self.rects = wall_rectangles(blank, self.max_walls)
        #: The sampled rule's walls as segments (:func:`~medc_training.envs.tl_sensing.wall_segments`),
        #: and which episodes' maps are made of them (else every line is sampled).
        self.segments, self.segments_ok = wall_segments(blank, self.max_walls)

    def start(self, walls: torch.Tensor, positions: torch.Tensor, readings: torch.Tensor,
              rows: torch.Tensor | None = None, rects: torch.Tensor | None = None) -> None:
        """Forget ``rows`` (all when None) and record the first readings of their new episodes
        (``rects``: their wall rectangles when the caller has them, else made from ``walls``)."""
        reading_map = torch.zeros((positions.shape[0], self.grid, self.grid), device=self.device)
        visit_map = torch.zeros_like(reading_map)
        scale = self.sensing.max_rate
        update_memory(reading_map, visit_map, positions, readings, scale)
        segments = segments_ok = None
        if self.sensing.line != "exact":
            rects = None
            if self.estimator is not None:
                segments, segments_ok = wall_segments(walls, self.max_walls)
        elif rects is None:
            rects = wall_rectangles(walls, self.max_walls)
        log_post = post = None
        if self.estimator is not None:
            log_post = self.estimator.prior(walls)
            post = self._posterior_buffer(positions.shape[0])
            whole = segments_ok is not None and bool(segments_ok.all())
            if not self.estimator.update(log_post, walls, positions, readings, rects,
                                         segments if whole else None, posterior_out=post):
                post = None
        cached = self._cached_posterior()
        if rows is None:
            self.reading_map, self.visit_map = reading_map, visit_map
            if log_post is not None:
                self.log_post = log_post
            if rects is not None:
                self.rects = rects
            if segments is not None:
                self.segments, self.segments_ok = segments, segments_ok
        else:
            self.reading_map[rows], self.visit_map[rows] = reading_map, visit_map
            if log_post is not None:
                self.log_post[rows] = log_post
            if rects is not None:
                self.rects[rows] = rects
            if segments is not None:
                self.segments[rows], self.segments_ok[rows] = segments, segments_ok
        if post is not None and rows is not None:
            if cached is None:
                post = None
            else:  # a fresh tensor: one posterior() handed out stays as it was
                cached = cached.clone()
                cached[rows] = post
                post = cached
        self._keep_posterior(post)

    def _posterior_buffer(self, k: int) -> torch.Tensor | None:
        fused = self.estimator.path == "fused"  # the levels' pass, or the one-level native kernel
        return torch.empty((k, self.grid * self.grid), device=self.device) if fused else None

    def _keep_posterior(self, post: torch.Tensor | None) -> None:
        self._post = post
        self._post_key = None if post is None else (self.log_post.data_ptr(), self.log_post._version)

    def _cached_posterior(self) -> torch.Tensor | None:
        """The kept marginal posterior while ``log_post`` is unchanged since, else None."""
        if self._post is None or self.log_post is None:
            return None
        if self._post_key != (self.log_post.data_ptr(), self.log_post._version):
            return None
        return self._post

    def record(self, walls: torch.Tensor, positions: torch.Tensor, readings: torch.Tensor) -> None:
        """Record one team step's readings (every episode of the batch)."""
        update_memory(self.reading_map, self.visit_map, positions, readings, self.sensing.max_rate)
        if self.estimator is None:
            return
        post = self._posterior_buffer(positions.shape[0])
        if self.sensing.line == "exact":
            done = self.estimator.update(self.log_post, walls, positions, readings, self.rects,
                                         posterior_out=post)
        else:
            segments = self.segments if bool(self.segments_ok.all()) else None
            done = self.estimator.update(self.log_post, walls, positions, readings, segments=segments,
                                         posterior_out=post)
        self._keep_posterior(post if done else None)

    def posterior(self) -> torch.Tensor | None:
        """float32 [B,G²] the source posterior (a fresh tensor), or None when this memory keeps none."""
        if self.estimator is None:
            return None
        cached = self._cached_posterior()
        return self.estimator.posterior(self.log_post) if cached is None else cached.clone()

    def _posterior(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        cached = self._cached_posterior()
        if cached is not None:
            return cached if rows is None else cached[rows]
        return self.estimator.posterior(self.log_post if rows is None else self.log_post[rows])

    def estimate_map(self) -> torch.Tensor | None:
        """float32 [B,G,G] source-estimate map, or None when the observation has none."""
        return None if self.estimator is None else self._estimate_map(self._posterior())

    def _estimate_map(self, p: torch.Tensor) -> torch.Tensor:
        est = self.estimator
        e = (1.0 - est.expected_from_posterior(p) * est.scale).clamp_(0.0, 1.0)
        return e.view(-1, self.grid, self.grid)

    def posterior_map(self) -> torch.Tensor | None:
        """float32 [B,G,G] the map the ``+posterior`` views show, p(s) / max_s p(s) per cell, or None
        when this memory keeps no posterior."""
        return None if self.estimator is None else self._posterior_map(self._posterior())

    def _posterior_map(self, p: torch.Tensor) -> torch.Tensor:
        return (p / p.amax(1, keepdim=True)).view(-1, self.grid, self.grid)

    def information_map(self, positions: torch.Tensor, walls: torch.Tensor,
                        rows: torch.Tensor | None = None) -> torch.Tensor | None:
        """float32 [B,G,G] ([R,G,G] of ``rows``) the map the ``+information`` views show, or None when
        this memory keeps no posterior: at every free cell a member of the team stands on or can move
        to next, the share of a reading's variance there that the unknown source cell explains,
        Var / (E + Var), with E and Var the mean and variance over the posterior of the reading's
        rate (the sensing model's, at the posterior-mean strength and background) and E also the
        reading's Poisson noise; 0 at every other cell. A cell where the hypotheses agree tells
        nothing (0); one where they differ far more than the counting noise approaches 1. Cheap: one
        geometric factor per (candidate cell, source cell), no quadrature.

        positions int64 [B,N,2] and walls [B,G,G] of the whole batch (as :meth:`observe` takes them).
        """
        if self.estimator is None:
            return None
        if rows is not None:
            positions, walls = positions[rows], walls[rows]
        est, g = self.estimator, self.grid
        k, n = positions.shape[:2]
        p = self._posterior(rows)  # [K, G²]
        log_post = self.log_post if rows is None else self.log_post[rows]
        if log_post.dim() == 2:
            strength = est.level_strength[0].expand(k)
            background = est.level_background[0].expand(k)
        else:  # the posterior means of the strength and background levels (the update keeps every
            # episode's largest log weight at 0, so the weights' exp cannot overflow; those below
            # e^-30 count as e^-30, which moves no mean and keeps exp off its slow near-underflow path)
            cells_major = log_post.transpose(1, 2)  # [K, G², L]: contiguous on the fused path
            w = cells_major.clamp(min=-30.0).exp_().sum(1)  # [K, L]
            w = w / w.sum(1, keepdim=True)
            strength, background = w @ est.level_strength, w @ est.level_background
        steps = torch.cat((torch.zeros((1, 2), dtype=torch.long, device=self.device),
                           action_deltas(self.device)))
        cand = (positions.unsqueeze(2) + steps).clamp_(0, g - 1).view(k, n * len(steps), 2)
        blocked = walls.bool() if walls.dtype == torch.bool else walls > 0.5
        mean_f, square_f = self._factor_moments(p, cand, blocked, rows)
        var = strength.view(-1, 1) ** 2 * (square_f - mean_f * mean_f).clamp_(min=0.0)
        mean = strength.view(-1, 1) * mean_f + background.view(-1, 1)
        share = var / (mean + var).clamp_(min=1e-12)
        cell = cand[..., 0] * g + cand[..., 1]  # [K, M]
        share = share.masked_fill_(blocked.view(k, -1).gather(1, cell), 0.0)
        out = torch.zeros((k, g * g), device=self.device).scatter_(1, cell, share)
        return out.view(k, g, g)

    def _factor_moments(self, p: torch.Tensor, cand: torch.Tensor, walls: torch.Tensor,
                        rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """float32 [K, M] each: the first two moments over posterior ``p`` [K, G²] of the geometric
        factor between each candidate cell ``cand`` int64 [K, M, 2] and every source cell; in one C
        pass per episode under the exact line rule where the kernel is there."""
        est = self.estimator
        if self.sensing.line == "exact":
            rects = (self.rects if rows is None else self.rects[rows]).to(torch.float32).contiguous()
            count = self.sensing.attenuation > 0.0
            cand = cand.contiguous()
            if tl_native.usable(p, cand, rects):
                est._levels_table(rects.shape[1] if count else 1)
                return tl_native.factor_moments(p.contiguous(), est._bag_factor, cand, rects, count,
                                                est._span)
            f = geometric_factor(self.sensing, cand, est.cells, walls, rects)
        else:
            f = geometric_factor(self.sensing, cand, est.cells, walls)  # [K, M, G²]
        pm = p.unsqueeze(1)
        return (f * pm).sum(-1), (f * f * pm).sum(-1)

    def source_maps(self, spec: ObservationSpec | None = None, rows: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The source-estimate map and the source-posterior map, float32 [B,G,G] ([R,G,G] of
        ``rows``), that view ``spec`` (default: this memory's) shows: None for a map it does not
        show, and for both when this memory keeps no posterior. Both come from one posterior."""
        spec = self.spec if spec is None else spec
        if self.estimator is None or not (spec.estimate or spec.posterior):
            return None, None
        p = self._posterior(rows)
        return (self._estimate_map(p) if spec.estimate else None,
                self._posterior_map(p) if spec.posterior else None)

    def observe(self, positions: torch.Tensor, walls: torch.Tensor, out: torch.Tensor | None = None,
                rows: torch.Tensor | None = None) -> torch.Tensor:
        """Every agent's observation, float32 [B,N,C,H,W] (see :func:`observe`); with ``rows``
        only those episodes' ([R,N,C,H,W]; ``positions`` and ``walls`` are still the whole batch)."""
        estimate, posterior = self.source_maps(rows=rows)
        information = self.information_map(positions, walls, rows) if self.spec.information else None
        if rows is None:
            return observe(self.spec, positions, self.reading_map, self.visit_map, walls, estimate,
                           out=out, posterior_map=posterior, information_map=information)
        return observe(self.spec, positions[rows], self.reading_map[rows], self.visit_map[rows], walls[rows],
                       estimate, out=out, posterior_map=posterior, information_map=information)

    def observe_agent(self, positions: torch.Tensor, walls: torch.Tensor, index: int,
                      spec: ObservationSpec | None = None) -> torch.Tensor:
        """Agent ``index``'s row of :meth:`observe` of view ``spec`` (default: this memory's), alone."""
        spec = self.spec if spec is None else parse_observation(spec)
        estimate, posterior = self.source_maps(spec)
        information = self.information_map(positions, walls) if spec.information else None
        return observe_agent(spec, positions, index, self.reading_map, self.visit_map, walls, estimate,
                             posterior, information)


def observe(
    spec: ObservationSpec,
    positions: torch.Tensor,
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    walls: torch.Tensor,
    estimate: torch.Tensor | None = None,
    out: torch.Tensor | None = None,
    posterior_map: torch.Tensor | None = None,
    information_map: torch.Tensor | None = None,
) -> torch.Tensor:
    """Every agent's observation of variant ``spec``, float32 [B,N,C,H,W] in [0, 1].

    positions int64 [B,N,2]; reading_map, visit_map float32 [B,G,G] (:class:`TeamMemory`);
    walls bool or float [B,G,G]; estimate float32 [B,G,G] (required when ``spec.estimate``);
    posterior_map float32 [B,G,G] (:meth:`TeamMemory.posterior_map`; required when
    ``spec.posterior``); information_map float32 [B,G,G] (:meth:`TeamMemory.information_map`;
    required when ``spec.information``).
    """
    spec = parse_observation(spec)
    extra = _source_layers(spec, estimate, posterior_map, information_map)
    b, n = positions.shape[:2]
    g = walls.shape[-1]
    if spec.view == "maps":
        c = len(observation_channels(spec))
        if out is None:
            out = torch.empty((b, n, c, g, g), dtype=torch.float32, device=positions.device)
        if extra:  # build_observations writes only into a contiguous 5-channel buffer
            out[:, :, :5].copy_(build_observations(positions, reading_map, visit_map, walls))
            for i, source_map in enumerate(extra):
                out[:, :, 5 + i].copy_(source_map.unsqueeze(1))
        else:
            build_observations(positions, reading_map, visit_map, walls, out=out)
        return out
    r = spec.radius
    side = 2 * r + 1
    # Team-wide maps: walls (off-grid = wall), team count, readings, visits, estimate, posterior;
    # each agent sees them in a window centred on itself (grid.team_windows).
    layers = [walls.to(torch.float32), _team_count(positions, g), reading_map, visit_norm(visit_map), *extra]
    stack = torch.stack(layers, dim=1)  # [B,C,G,G]
    c = stack.shape[1]
    outside = torch.zeros(c, device=positions.device)
    outside[0] = 1.0
    win = team_windows(stack, positions, r, outside)
    if out is None:
        out = torch.empty((b, n, c, side, side), dtype=torch.float32, device=positions.device)
    out.copy_(win)
    # The team channel counts the others: remove the agent itself from its own centre cell.
    out[:, :, 1, r, r] -= 1.0
    out[:, :, 1].clamp_(0.0, 1.0)
    return out


def _source_layers(spec: ObservationSpec, estimate: torch.Tensor | None, posterior_map: torch.Tensor | None,
                   information_map: torch.Tensor | None) -> list[torch.Tensor]:
    """The team's source maps view ``spec`` shows, in channel order (after the application's own);
    ValueError naming the first one it needs and was not given."""
    if spec.estimate and estimate is None:
        raise ValueError(f"observation {spec.name} needs the source estimate map")
    if spec.posterior and posterior_map is None:
        raise ValueError(f"observation {spec.name} needs the source posterior map (posterior_map)")
    if spec.information and information_map is None:
        raise ValueError(f"observation {spec.name} needs the information map (information_map)")
    return (([estimate] if spec.estimate else []) + ([posterior_map] if spec.posterior else [])
            + ([information_map] if spec.information else []))


def _team_count(positions: torch.Tensor, g: int) -> torch.Tensor:
    """float32 [B,G,G]: how many members of the team stand on each cell (positions int64 [B,N,2])."""
    cell = positions[..., 0] * g + positions[..., 1]  # [B,N]
    count = torch.zeros((positions.shape[0], g * g), device=positions.device)
    return count.scatter_add_(1, cell, torch.ones(cell.shape, device=positions.device)).view(-1, g, g)


def observe_agent(
    spec: ObservationSpec,
    positions: torch.Tensor,
    index: int,
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    walls: torch.Tensor,
    estimate: torch.Tensor | None = None,
    posterior_map: torch.Tensor | None = None,
    information_map: torch.Tensor | None = None,
) -> torch.Tensor:
    """Agent ``index``'s observation of variant ``spec``, float32 [B,C,H,W]: the same values as
    ``observe(spec, positions, ...)[:, index]`` with the same arguments, built for that agent alone.

    An agent node decides for one agent: rather than gathering every agent's window cell by cell
    (:func:`observe`), the team's maps are written once into a grid padded with the off-grid values
    (a wall; nothing else) and the agent's window is one slice of it, a handful of tensor operations
    whatever the window's size. The whole-grid view (``maps``) is :func:`observe`'s row.
    """
    spec = parse_observation(spec)
    if spec.view == "maps":
        return observe(spec, positions, reading_map, visit_map, walls, estimate,
                       posterior_map=posterior_map, information_map=information_map)[:, index]
    extra = _source_layers(spec, estimate, posterior_map, information_map)
    b, g, r = positions.shape[0], walls.shape[-1], spec.radius
    side = 2 * r + 1
    layers = [walls, _team_count(positions, g), reading_map, visit_norm(visit_map), *extra]
    padded = torch.zeros((b, len(layers), g + 2 * r, g + 2 * r), device=positions.device)
    padded[:, 0] = 1.0  # off the grid is a wall
    inner = padded[:, :, r:r + g, r:r + g]
    for i, layer in enumerate(layers):
        inner[:, i].copy_(layer)
    out = torch.empty((b, len(layers), side, side), device=positions.device)
    # A window centred on (y, x) of the grid starts at (y, x) of the padded grid.
    for k, (y, x) in enumerate(positions[:, index].tolist()):
        out[k].copy_(padded[k, :, y:y + side, x:x + side])
    # The team channel counts the others: remove the agent itself from its own centre cell.
    out[:, 1, r, r] -= 1.0
    out[:, 1].clamp_(0.0, 1.0)
    return out
