"""Target-localization observations: the declared variants, the team's source estimate, the builder.

One pure builder serves the batched core, the PettingZoo env, the experts and the ROS agent
node: each keeps the same team memory (:class:`TeamMemory`: latest normalised reading and visit
count per cell, and the log posterior over source cells) and calls :func:`observe` on it.

Variants (:class:`ObservationSpec`, written as a short name on the command line and as a dict in
every bundle manifest):

``maps``
    The paper's 5 absolute maps G×G: own location, team locations, readings, visit counts,
    walls (:data:`MAP_CHANNELS`).
``maps+estimate``
    The same plus a 6th map, the team's source estimate (below).
``egoR`` / ``egoR+estimate`` (R = window radius, e.g. ``ego6+estimate``)
    An agent-centred window of (2R+1)×(2R+1) cells with the agent in the centre cell:
    walls (cells off the grid count as walls), other team members, readings, visit counts, and
    with ``+estimate`` the source estimate (:data:`EGO_CHANNELS`). Off-grid cells read 0 in every
    channel but walls. R = G−1 is the full re-centred view: every cell of the grid is in the window
    wherever the agent stands.

Source estimate (:class:`SourceEstimator`)
    The team's Bayes posterior over the source cell, from every reading the team has taken in the
    episode, with the environment's own sensor model (inverse square, wall attenuation along the
    line exactly as :func:`~medc_training.envs.target_localization.sensor_reading` computes it,
    background) and a Poisson counting likelihood::

        log p(s | r_1..r_t) = const + sum_k [ r_k log lambda_s(p_k) - lambda_s(p_k) ]

    over free cells s; the prior is uniform over free cells, and a cell some agent has stood on
    without the episode ending is not the source (probability 0). With ``noise=True`` the readings
    are Poisson counts and this is the exact posterior; without noise the readings equal the rates
    and the same formula is the posterior of a Poisson sensor (peaked at the true source). Log
    probabilities are kept relative to their maximum and floored at :data:`LOG_FLOOR`, below
    float32's smallest positive exp(), so the stored posterior equals the exact one to float32
    precision and a reading from a mismatched sensor can never leave the team with no candidate.

    It is shown as a smooth map, the expected number of moves to the source::

        E(c) = sum_s p(s) * max(|c_row - s_row|, |c_col - s_col|)       (Chebyshev: 8 moves)
        estimate(c) = 1 - E(c) / (G - 1)                                  in [0, 1]

    Walls are ignored in E (they are in the walls channel); 1 marks the cell the team is sure of.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import torch

from medc_training.envs.grid import agent_windows
from medc_training.envs.tl_sensing import (
    CHANNELS,
    build_observations,
    rates_from_every_cell,
    update_memory,
    visit_norm,
)

__all__ = [
    "DEFAULT_OBSERVATION",
    "EGO_CHANNELS",
    "LOG_FLOOR",
    "MAP_CHANNELS",
    "OBSERVATION_NAMES",
    "ObservationSpec",
    "SourceEstimator",
    "TeamMemory",
    "observe",
    "parse_observation",
]

MAP_CHANNELS: tuple[str, ...] = CHANNELS
EGO_CHANNELS: tuple[str, ...] = ("walls", "team_locations", "readings", "visit_counts")
ESTIMATE_CHANNEL = "source_estimate"
#: Examples of accepted names (any radius 1..MAX_RADIUS is accepted for ego views).
OBSERVATION_NAMES: tuple[str, ...] = ("maps", "maps+estimate", "ego6", "ego6+estimate")
#: The observation a target-localization environment produces unless told otherwise. Chosen by
#: measurement (docs/environments.md, "Observations").
DEFAULT_OBSERVATION = "ego6+estimate"
#: Relative log-probability floor of the source posterior (exp(-104) underflows float32 to 0).
LOG_FLOOR = -104.0
#: Largest reading the estimator takes (counts/s): 1000x the model's highest rate, S + BG = 1001.
MAX_READING = 1e6
MAX_RADIUS = 255
#: Largest temporary (elements) of one expected-distance chunk.
_CHUNK_ELEMENTS = 1 << 23
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

    @property
    def channels(self) -> tuple[str, ...]:
        base = MAP_CHANNELS if self.view == "maps" else EGO_CHANNELS
        return base + ((ESTIMATE_CHANNEL,) if self.estimate else ())

    def shape(self, grid: int) -> tuple[int, int, int]:
        """(C, H, W) of one agent's observation on a ``grid``×``grid`` area."""
        side = grid if self.view == "maps" else 2 * self.radius + 1
        return (len(self.channels), side, side)

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


class SourceEstimator:
    """The team's Bayes posterior over the source cell on a ``grid``×``grid`` area (module docstring).

    Stateless apart from per-grid constants; the posterior lives in a ``log_post`` tensor
    float32 [B, G*G] that the caller owns (:class:`TeamMemory`).
    """

    def __init__(self, grid: int, device: torch.device | str) -> None:
        self.grid = int(grid)
        self.device = torch.device(device)
        g = self.grid
        idx = torch.arange(g * g, device=self.device)
        self.cells = torch.stack((idx // g, idx % g), dim=-1)  # [G²,2] (row, col)
        diff = (self.cells.unsqueeze(1) - self.cells.unsqueeze(0)).abs()
        # Chebyshev distance between every pair of cells: the moves needed without walls.
        self.moves = diff.max(-1).values.to(torch.float32)  # [G²,G²]
        self.scale = 1.0 / max(1, g - 1)

    def prior(self, walls: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²] log prior: 0 on free cells, LOG_FLOOR on walls."""
        k = walls.shape[0]
        return torch.zeros((k, self.grid * self.grid), device=self.device).masked_fill_(
            walls.reshape(k, -1).bool(), LOG_FLOOR
        )

    def update(self, log_post: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor,
               readings: torch.Tensor) -> None:
        """Fold the team's readings at ``positions`` (int64 [K,N,2]) into ``log_post`` in place.

        walls bool [K,G,G]; readings float32 [K,N] (counts/s, as :func:`sensor_reading` returns).
        """
        k = positions.shape[0]
        # No sensor of this model reads more than MAX_READING; a larger (or infinite) value from a
        # mismatched or faulty sensor is taken as MAX_READING, so the float32 sums below stay finite.
        readings = torch.nan_to_num(readings, nan=0.0, posinf=MAX_READING).clamp(0.0, MAX_READING)
        rate = rates_from_every_cell(positions, walls)  # [K,N,G²]: the simulator's sensor model
        loglik = (readings.unsqueeze(-1) * torch.log(rate) - rate).sum(1)  # [K,G²]
        log_post.add_(loglik)
        # Standing on a cell without the episode ending rules it out as the source.
        g = self.grid
        log_post.scatter_(1, positions[..., 0] * g + positions[..., 1], LOG_FLOOR)
        log_post.masked_fill_(walls.reshape(k, -1).bool(), LOG_FLOOR)
        log_post.sub_(log_post.max(1, keepdim=True).values).clamp_(min=LOG_FLOOR)

    @staticmethod
    def posterior(log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²] posterior probabilities (floored cells get exactly 0)."""
        p = torch.exp(log_post).masked_fill_(log_post <= LOG_FLOOR, 0.0)
        return p / p.sum(1, keepdim=True)

    def expected_moves(self, log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G²]: E(c), the posterior-expected Chebyshev distance to the source.

        A broadcast product summed per row rather than a matrix product: BLAS blocks a matrix
        product differently for different K, so one episode's estimate would depend (in the last
        bit) on how many episodes are batched with it; this way it never does.
        """
        p = self.posterior(log_post)
        cells = self.moves.shape[0]
        rows = max(1, _CHUNK_ELEMENTS // (cells * cells))
        out = torch.empty_like(p)
        for i in range(0, p.shape[0], rows):
            out[i:i + rows] = (p[i:i + rows].unsqueeze(1) * self.moves).sum(-1)
        return out

    def estimate_map(self, log_post: torch.Tensor) -> torch.Tensor:
        """float32 [K, G, G]: 1 - E(c)/(G-1), the map the observations show."""
        k = log_post.shape[0]
        e = (1.0 - self.expected_moves(log_post) * self.scale).clamp_(0.0, 1.0)
        return e.view(k, self.grid, self.grid)


class TeamMemory:
    """What a team knows in B episodes at once: the memory the observations are built from.

    ``reading_map`` float32 [B,G,G] (latest normalised reading per cell, 0 = never visited),
    ``visit_map`` float32 [B,G,G] (raw visit counts), ``log_post`` float32 [B,G²] (the source
    posterior, only kept when the observation shows the estimate). The batched core, the PettingZoo
    env and the ROS agent node hold one each and feed it the same readings.
    """

    def __init__(self, spec: ObservationSpec, batch: int, grid: int, device: torch.device | str) -> None:
        self.spec = parse_observation(spec)
        self.grid = int(grid)
        self.device = torch.device(device)
        g = self.grid
        self.reading_map = torch.zeros((batch, g, g), device=self.device)
        self.visit_map = torch.zeros((batch, g, g), device=self.device)
        self.estimator = SourceEstimator(g, self.device) if self.spec.estimate else None
        self.log_post = torch.zeros((batch, g * g), device=self.device) if self.spec.estimate else None

    def start(self, walls: torch.Tensor, positions: torch.Tensor, readings: torch.Tensor,
              rows: torch.Tensor | None = None) -> None:
        """Forget ``rows`` (all when None) and record the first readings of their new episodes."""
        reading_map = torch.zeros((positions.shape[0], self.grid, self.grid), device=self.device)
        visit_map = torch.zeros_like(reading_map)
        update_memory(reading_map, visit_map, positions, readings)
        log_post = None
        if self.estimator is not None:
            log_post = self.estimator.prior(walls)
            self.estimator.update(log_post, walls, positions, readings)
        if rows is None:
            self.reading_map, self.visit_map = reading_map, visit_map
            if log_post is not None:
                self.log_post = log_post
        else:
            self.reading_map[rows], self.visit_map[rows] = reading_map, visit_map
            if log_post is not None:
                self.log_post[rows] = log_post

    def record(self, walls: torch.Tensor, positions: torch.Tensor, readings: torch.Tensor) -> None:
        """Record one team step's readings (every episode of the batch)."""
        update_memory(self.reading_map, self.visit_map, positions, readings)
        if self.estimator is not None:
            self.estimator.update(self.log_post, walls, positions, readings)

    def estimate_map(self) -> torch.Tensor | None:
        """float32 [B,G,G] source-estimate map, or None when the observation has none."""
        return None if self.estimator is None else self.estimator.estimate_map(self.log_post)

    def observe(self, positions: torch.Tensor, walls: torch.Tensor, out: torch.Tensor | None = None,
                rows: torch.Tensor | None = None) -> torch.Tensor:
        """Every agent's observation, float32 [B,N,C,H,W] (see :func:`observe`); with ``rows``
        only those episodes' ([R,N,C,H,W]; ``positions`` and ``walls`` are still the whole batch)."""
        if rows is None:
            return observe(self.spec, positions, self.reading_map, self.visit_map, walls,
                           self.estimate_map(), out=out)
        est = None if self.estimator is None else self.estimator.estimate_map(self.log_post[rows])
        return observe(self.spec, positions[rows], self.reading_map[rows], self.visit_map[rows], walls[rows],
                       est, out=out)


def observe(
    spec: ObservationSpec,
    positions: torch.Tensor,
    reading_map: torch.Tensor,
    visit_map: torch.Tensor,
    walls: torch.Tensor,
    estimate: torch.Tensor | None = None,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Every agent's observation of variant ``spec``, float32 [B,N,C,H,W] in [0, 1].

    positions int64 [B,N,2]; reading_map, visit_map float32 [B,G,G] (:class:`TeamMemory`);
    walls bool or float [B,G,G]; estimate float32 [B,G,G] (required when ``spec.estimate``).
    """
    spec = parse_observation(spec)
    if spec.estimate and estimate is None:
        raise ValueError(f"observation {spec.name} needs the source estimate map")
    b, n = positions.shape[:2]
    g = walls.shape[-1]
    if spec.view == "maps":
        c = len(spec.channels)
        if out is None:
            out = torch.empty((b, n, c, g, g), dtype=torch.float32, device=positions.device)
        if spec.estimate:  # build_observations writes only into a contiguous 5-channel buffer
            out[:, :, :5].copy_(build_observations(positions, reading_map, visit_map, walls))
            out[:, :, 5].copy_(estimate.unsqueeze(1))
        else:
            build_observations(positions, reading_map, visit_map, walls, out=out)
        return out
    r = spec.radius
    side = 2 * r + 1
    # Team-wide maps: walls (off-grid = wall), team count, readings, visits, estimate; each agent
    # sees them in a window centred on itself (grid.agent_windows, shared with fleet and maze).
    layers = [walls.to(torch.float32), None, reading_map, visit_norm(visit_map)]
    if spec.estimate:
        layers.append(estimate)
    cell = positions[..., 0] * g + positions[..., 1]  # [B,N]
    count = torch.zeros((b, g * g), device=positions.device).scatter_add_(
        1, cell, torch.ones(cell.shape, device=positions.device))
    layers[1] = count.view(b, g, g)
    stack = torch.stack(layers, dim=1)  # [B,C,G,G]
    c = stack.shape[1]
    outside = torch.zeros(c, device=positions.device)
    outside[0] = 1.0
    win = agent_windows(stack.unsqueeze(1).expand(b, n, c, g, g), positions, r, outside)
    if out is None:
        out = torch.empty((b, n, c, side, side), dtype=torch.float32, device=positions.device)
    out.copy_(win)
    # The team channel counts the others: remove the agent itself from its own centre cell.
    out[:, :, 1, r, r] -= 1.0
    out[:, :, 1].clamp_(0.0, 1.0)
    return out

