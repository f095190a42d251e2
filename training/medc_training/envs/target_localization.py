"""Target localization (paper Section V-A, notation ``AyWz``): a team finds a radioactive source.

A G x G grid with random walls, 8 moves, a sensor whose rate falls with the squared distance and
halves through each wall, the paper's 5 maps per agent and a sparse team reward on the target. The
pure functions :func:`sensor_reading`, :func:`update_memory` and :func:`build_observations` (from
:mod:`medc_training.envs.tl_sensing`, re-exported) are what the ROS nodes call on topic data and
the batched core below calls too. The world, readings and rewards: docs/environments.md,
"Target localization".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from medc_training.envs.core import (
    BatchedEnv,
    EnvState,
    check_bool,
    check_core_options,
    check_int,
)
from medc_training.envs.descriptor import Application, register
from medc_training.envs.grid import (
    ACTION_NAMES,
    ACTIONS,
    OPPOSITE,
    action_deltas,
    bfs_distance,
    gather_cells,
    neighbour_index,
    pad_blocked,
    random_free_cells,
)
from medc_training.envs.names import TARGET_LOCALIZATION
from medc_training.envs.tl_observation import (
    DEFAULT_OBSERVATION,
    TeamMemory,
    observation_channels,
    observation_shape,
    parse_observation,
)
from medc_training.envs.tl_sensing import (
    BACKGROUND,
    CHANNELS,
    DEFAULT_SENSING,
    SENSING_PRESETS,
    SOURCE_STRENGTH,
    VISIT_SATURATION,
    WALL_ATTENUATION,
    SensingModel,
    build_observations,
    expected_rate_from_sources,
    normalise_reading,
    parse_sensing,
    rates_from_every_cell,
    realistic_rates,
    sensor_reading,
    update_memory,
    visit_norm,
    wall_rectangles,
)

__all__ = [
    "ACTIONS",
    "ACTION_NAMES",
    "APPLICATION",
    "BACKGROUND",
    "CHANNELS",
    "DEFAULT_OBSERVATION",
    "OPPOSITE",
    "SHAPING_SCALE",
    "SOURCE_STRENGTH",
    "SUCCESS_REWARD",
    "VISIT_SATURATION",
    "WALL_ATTENUATION",
    "TargetLocalization",
    "TargetLocalizationState",
    "build_observations",
    "check_options",
    "expected_rate_from_sources",
    "generate_layouts",
    "max_walls",
    "normalise_reading",
    "rates_from_every_cell",
    "sensor_reading",
    "update_memory",
    "visit_norm",
    "wall_length_range",
]

SUCCESS_REWARD = 10.0
SHAPING_SCALE = 0.1
_MAX_GRID = 256
_MAX_AGENTS = 64


def wall_length_range(grid: int) -> tuple[int, int]:
    """(shortest, longest) wall segment length, in cells, on a ``grid``×``grid`` area."""
    lo = max(2, grid // 6)
    return lo, max(lo, grid // 3)


def max_walls(grid: int) -> int:
    """Most wall segments a ``grid``×``grid`` area accepts.

    Each segment with the one-cell clearance around it may cover 3 × (longest + 2) cells;
    together they may cover at most a third of the area, so that random placement of
    non-touching segments succeeds quickly.
    """
    _, longest = wall_length_range(grid)
    return (grid * grid) // (3 * 3 * (longest + 2))


def check_options(agents: int, walls: int, grid: int, max_steps: int) -> tuple[int, int, int, int]:
    """Validate the scenario options (the cores' shared check, then the walls); raise ValueError
    saying what is allowed."""
    grid, agents, max_steps = check_core_options(
        grid, agents, max_steps, grid_range=(5, _MAX_GRID), max_agents=lambda g: min(_MAX_AGENTS, g * g // 4)
    )
    walls = check_int("walls", walls, 0, max_walls(grid))
    return agents, walls, grid, max_steps


def generate_layouts(
    count: int,
    grid: int,
    walls: int,
    agents: int,
    generator: torch.Generator,
    device: torch.device,
) -> dict[str, torch.Tensor]:
    """Sample ``count`` random episode layouts at once (vectorised rejection sampling).

    Returns ``walls`` bool [K,G,G], ``target`` int64 [K,2], ``positions`` int64 [K,N,2]
    and ``distance`` float32 [K,G,G] (BFS moves to the target around walls; inf on walls).
    """
    lo, hi = wall_length_range(grid)
    wall_map = torch.zeros((count, grid, grid), dtype=torch.bool, device=device)
    target = torch.zeros((count, 2), dtype=torch.long, device=device)
    positions = torch.zeros((count, agents, 2), dtype=torch.long, device=device)
    distance = torch.empty((count, grid, grid), dtype=torch.float32, device=device)
    todo = torch.arange(count, device=device)
    for _attempt in range(10_000):
        k = len(todo)
        if walls > 0:
            wm = _sample_walls(k, grid, walls, lo, hi, generator, device)
        else:
            wm = torch.zeros((k, grid, grid), dtype=torch.bool, device=device)
        free = ~wm
        cells = random_free_cells(free, agents + 1, generator)
        src = torch.zeros_like(free)
        src.view(k, -1)[torch.arange(k, device=device), cells[:, 0, 0] * grid + cells[:, 0, 1]] = True
        d = bfs_distance(free, src)
        wall_map[todo], target[todo], positions[todo], distance[todo] = wm, cells[:, 0], cells[:, 1:], d
        # Connected: every free cell was reached from the target.
        bad = (torch.isinf(d) & free).flatten(1).any(1)
        if not bool(bad.any()):
            return {"walls": wall_map, "target": target, "positions": positions, "distance": distance}
        todo = todo[bad]
    raise RuntimeError("could not place non-touching, connected walls; use fewer walls or a larger grid")


def _sample_walls(
    count: int, grid: int, walls: int, lo: int, hi: int, generator: torch.Generator, device: torch.device
) -> torch.Tensor:
    """bool [count,G,G] maps of ``walls`` non-touching axis-aligned segments each."""
    segs = torch.empty((count, walls, 4), dtype=torch.long, device=device)
    todo = torch.arange(count, device=device)
    for _attempt in range(10_000):
        k = len(todo)
        u = torch.rand((k, walls, 4), generator=generator, device=device)
        length = lo + (u[..., 0] * (hi - lo + 1)).long().clamp_(max=hi - lo)
        vertical = u[..., 1] < 0.5
        span_r = torch.where(vertical, length, 1)
        span_c = torch.where(vertical, 1, length)
        r0 = (u[..., 2] * (grid - span_r + 1)).long()
        c0 = (u[..., 3] * (grid - span_c + 1)).long()
        segs[todo] = torch.stack((r0, c0, r0 + span_r - 1, c0 + span_c - 1), dim=-1)
        s = segs[todo]
        a, b_ = s.unsqueeze(2), s.unsqueeze(1)  # [k,Z,1,4], [k,1,Z,4]
        gap_r = torch.maximum(b_[..., 0] - a[..., 2], a[..., 0] - b_[..., 2])
        gap_c = torch.maximum(b_[..., 1] - a[..., 3], a[..., 1] - b_[..., 3])
        # Two segments touch (or overlap) when their Chebyshev gap is at most one cell.
        touch = torch.maximum(gap_r, gap_c) <= 1
        touch &= ~torch.eye(walls, dtype=torch.bool, device=device)
        bad = touch.flatten(1).any(1)
        if not bool(bad.any()):
            break
        todo = todo[bad]
    else:
        raise RuntimeError("could not place non-touching walls; use fewer walls or a larger grid")
    rows = torch.arange(grid, device=device)
    in_r = (rows >= segs[..., 0:1]) & (rows <= segs[..., 2:3])  # [K,Z,G]
    in_c = (rows >= segs[..., 1:2]) & (rows <= segs[..., 3:4])
    return (in_r.unsqueeze(-1) & in_c.unsqueeze(-2)).any(1)


def check_noise(sensing: SensingModel, noise: bool | None) -> bool:
    """Whether readings are Poisson counts: ``noise``, or the sensing model's when None
    (ValueError for False under a model that always counts them)."""
    noise = check_bool("noise", sensing.noise if noise is None else noise)
    if sensing.noise and not noise:
        raise ValueError(f"the {sensing.name} sensing model always counts Poisson noise; "
                         "leave noise unset (or True)")
    return noise


@dataclass(frozen=True)
class TargetLocalizationState(EnvState):
    """:class:`EnvState` of a target-localization environment, plus what a real UAV team would
    publish and the core keeps internal (copies, like every field of EnvState).

    target:   the source's cell (row, col).
    walls:    bool [G,G] wall cells of the current episode.
    readings: each agent's raw reading (counts/s, noise included) at its current cell: exactly
              what the core recorded in its memory.
    """

    target: tuple[int, int]
    walls: torch.Tensor
    readings: tuple[float, ...]


class TargetLocalization(BatchedEnv):
    """Batched target localization core (see the module docstring for the rules).

    ``make_batched("target_localization", num_envs=B, device="cpu", seed=0, agents=3,
    walls=2, grid=30, max_steps=100, reward_shaping=False, noise=False, copy_obs=True)``.

    A simulator reads environment ``b`` through :meth:`state` (a :class:`TargetLocalizationState`
    of copies: step, positions, mask, target, walls, raw readings), never by touching the
    state tensors (``positions`` [B,N,2], ``target`` [B,2], ``walls`` bool [B,G,G], ``distance``
    [B,G,G] (BFS field), ``t`` [B], ``mask`` [B,N,A], ``readings`` [B,N], the memory's
    ``reading_map``/``visit_map`` [B,G,G]).

    The observations live in one buffer each step updates in place (only the agents' old and new
    cells; rebuilt for environments that reset). ``copy_obs=True`` (default) returns fresh
    ``obs`` and ``final_obs``; ``copy_obs=False`` returns that buffer and a reused final-obs
    buffer, valid until the next ``step``/``reset``: the fast path for loops that copy anyway.
    """

    name = TARGET_LOCALIZATION

    def __init__(
        self,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        agents: int = 3,
        walls: int = 2,
        grid: int = 30,
        max_steps: int = 100,
        reward_shaping: bool = False,
        noise: bool | None = None,
        copy_obs: bool = True,
        observation: str = DEFAULT_OBSERVATION,
        sensing: str | dict | SensingModel = DEFAULT_SENSING,
        posterior: bool = False,
        end_on_find: bool = True,
    ) -> None:
        self.num_agents, self.num_walls, self.grid, self.max_steps = check_options(
            agents, walls, grid, max_steps
        )
        self.reward_shaping = check_bool("reward_shaping", reward_shaping)
        self.sensing = parse_sensing(sensing)
        self.noise = check_noise(self.sensing, noise)
        self.copy_obs = check_bool("copy_obs", copy_obs)
        super().__init__(num_envs, device, seed)
        self.num_actions = len(ACTIONS)
        self.observation = parse_observation(observation)
        self.obs_shape = observation_shape(self.observation, self.grid)
        # The paper's maps change in a few cells per step and are updated in place
        # (_observe_step); every other observation is rebuilt from the team memory each step.
        b, n = self.num_envs, self.num_agents
        maps_size = len(CHANNELS) * self.grid ** 2
        self._agent_base = torch.arange(b * n, device=self.device).view(b, n) * maps_size
        self._others = ~torch.eye(n, dtype=torch.bool, device=self.device)
        #: Finding the source ends the episode (success). False: only ``max_steps`` or the caller
        #: (:meth:`end_episode`, e.g. on the team's declaration) ends it, ``success`` is never set,
        #: and the team's estimate no longer rules out the cells the agents have stood on.
        self.end_on_find = check_bool("end_on_find", end_on_find)
        self.memory = TeamMemory(self.observation, self.num_envs, self.grid, self.device, self.sensing,
                                 posterior=check_bool("posterior", posterior), max_walls=self.num_walls,
                                 rule_out=self.end_on_find)
        self._deltas = action_deltas(self.device)
        # Layouts are generated in chunks and handed out on reset: one batched BFS serves
        # many episodes, so auto-resets cost little inside the step loop.
        self._chunk = max(64, self.num_envs)
        self._pool: dict[str, torch.Tensor] | None = None
        self._pool_next = 0
        self._started = False

    @property
    def attributes(self) -> dict[str, Any]:
        return {
            "agents": self.num_agents,
            "walls": self.num_walls,
            "grid": self.grid,
            "max_steps": self.max_steps,
            # The paper-simple model is the one every committed bundle and registry entry assumes.
            **({} if self.sensing.name == DEFAULT_SENSING else {"sensing": self.sensing.name}),
        }

    @property
    def reading_map(self) -> torch.Tensor:
        """float32 [B,G,G] the team's latest normalised reading per cell (0 = never visited)."""
        return self.memory.reading_map

    @property
    def visit_map(self) -> torch.Tensor:
        """float32 [B,G,G] the team's raw visit count per cell."""
        return self.memory.visit_map

    # -- episode layouts -------------------------------------------------------------------
    def _take_layouts(self, k: int) -> dict[str, torch.Tensor]:
        if self._pool is None or self._pool_next + k > len(self._pool["target"]):
            fresh = generate_layouts(
                max(self._chunk, k), self.grid, self.num_walls, self.num_agents, self.generator, self.device
            )
            if not self.sensing.known:  # the episode's source strength and background, unknown to the team
                count = len(fresh["target"])
                u = torch.rand((2, count), generator=self.generator, device=self.device)
                (s_lo, s_hi), (b_lo, b_hi) = self.sensing.strength, self.sensing.background
                fresh["strength"] = s_lo + (s_hi - s_lo) * u[0]
                fresh["background"] = b_lo + (b_hi - b_lo) * u[1]
            if self.sensing.line == "exact":  # each wall segment's rectangle, for the line of sight
                fresh["rects"] = wall_rectangles(fresh["walls"], max(1, self.num_walls))
            if self._pool is not None and self._pool_next < len(self._pool["target"]):
                fresh = {key: torch.cat((self._pool[key][self._pool_next :], v)) for key, v in fresh.items()}
            self._pool, self._pool_next = fresh, 0
        out = {key: v[self._pool_next : self._pool_next + k] for key, v in self._pool.items()}
        self._pool_next += k
        return out

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        """Load fresh layouts into ``rows`` (all environments when None) and take first readings."""
        k = self.num_envs if rows is None else len(rows)
        lay = self._take_layouts(k)
        blocked = pad_blocked(lay["walls"])
        dist_pad = torch.nn.functional.pad(lay["distance"], (1, 1, 1, 1), value=float("inf"))
        readings = self._read(lay)
        self.memory.start(lay["walls"], lay["positions"], readings, rows, lay.get("rects"))
        team_dist = gather_cells(lay["distance"], lay["positions"]).mean(1)
        if rows is None:
            self.walls, self.blocked_pad, self.dist_pad = lay["walls"].clone(), blocked, dist_pad
            self.distance = lay["distance"].clone()
            self.target, self.positions = lay["target"].clone(), lay["positions"].clone()
            self.walls_f = lay["walls"].float()
            self.team_dist = team_dist
            self.readings = readings
            self.strength, self.background = lay.get("strength"), lay.get("background")
            self.rects = lay.get("rects")
            self.t = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        else:
            self.walls[rows], self.blocked_pad[rows], self.dist_pad[rows] = lay["walls"], blocked, dist_pad
            self.distance[rows] = lay["distance"]
            self.target[rows], self.positions[rows] = lay["target"], lay["positions"]
            self.walls_f[rows] = lay["walls"].float()
            self.team_dist[rows] = team_dist
            self.readings[rows] = readings
            if self.strength is not None:
                self.strength[rows], self.background[rows] = lay["strength"], lay["background"]
            if self.rects is not None:
                self.rects[rows] = lay["rects"]
            self.t[rows] = 0

    def _reseeded(self) -> None:
        self._pool, self._pool_next = None, 0

    # -- the transition and the observation (the episode loop is BatchedEnv's) -------------
    def _read(self, lay: dict[str, torch.Tensor]) -> torch.Tensor:
        """The sensors' readings (counts/s) under the sensing model, for ``lay``'s positions,
        target, walls and (when the team does not know them) strength, background and wall
        rectangles."""
        if "strength" not in lay:  # paper-simple: the sampled line, known strength and background
            return sensor_reading(lay["positions"], lay["target"], lay["walls"], noise=self.noise,
                                  generator=self.generator)
        rate = realistic_rates(self.sensing, lay["positions"], lay["target"], lay["walls"], lay["strength"],
                               lay["background"], lay.get("rects"))
        return torch.poisson(rate, generator=self.generator) if self.noise else rate

    def _episode_state(self) -> dict[str, torch.Tensor]:
        """The current episodes' layout, as :meth:`_read` takes it."""
        state = {"positions": self.positions, "target": self.target, "walls": self.walls}
        if self.strength is not None:
            state.update(strength=self.strength, background=self.background)
        if self.rects is not None:
            state["rects"] = self.rects
        return state

    def found(self) -> torch.Tensor:
        """bool [B]: an agent is within the success radius of the source."""
        delta = self.positions - self.target.unsqueeze(1)
        return self.sensing.within_reach((delta * delta).sum(-1)).any(-1)

    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        found = self.found()
        readings = self._read(self._episode_state())
        self.memory.record(self.walls, self.positions, readings)
        self.readings = readings
        if not self.end_on_find:
            found = torch.zeros_like(found)
        reward = found.float() * SUCCESS_REWARD
        if self.reward_shaping:
            team_dist = gather_cells(self.distance, self.positions).mean(1)
            reward += SHAPING_SCALE * (self.team_dist - team_dist)
            self.team_dist = team_dist
        return reward, found

    def _observe(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        return self.memory.observe(self.positions, self.walls_f, rows=rows)

    def _observe_step(self, previous: torch.Tensor) -> None:
        if not self.observes_pictures:
            self.memory.observe(self.positions, self.walls_f, out=self._obs)
            return
        g = self.grid
        self._update_obs(previous[..., 0] * g + previous[..., 1],
                         self.positions[..., 0] * g + self.positions[..., 1])

    def _update_obs(self, old_cell: torch.Tensor, new_cell: torch.Tensor) -> None:
        """Apply one step's changes to the absolute maps (only the cells that changed)."""
        hw = self.grid * self.grid
        flat = self._obs.view(-1)
        # Flat offset of map 0 of agent (b, i) in the observation buffer, and of each map in it.
        base = self._agent_base  # [B,N]
        own, team, reading, visits = (CHANNELS.index(c) * hw for c in
                                      ("own_location", "team_locations", "readings", "visit_counts"))
        pair_old = base.unsqueeze(2) + old_cell.unsqueeze(1)  # [B,i,j]: agent i's map at j's cell
        pair_new = base.unsqueeze(2) + new_cell.unsqueeze(1)
        b = new_cell.shape[0]
        # Clear before set, so that an agent moving onto a cell another agent just left stays
        # marked. index_fill_/index_copy_ on the flat view are much cheaper than advanced
        # indexing; duplicate indices only ever carry equal values.
        flat.index_fill_(0, (base + old_cell).view(-1) + own, 0.0)
        flat.index_fill_(0, (base + new_cell).view(-1) + own, 1.0)
        if self.num_agents > 1:
            flat.index_fill_(0, pair_old[:, self._others].view(-1) + team, 0.0)
            flat.index_fill_(0, pair_new[:, self._others].view(-1) + team, 1.0)
        readings = self.reading_map.view(b, -1).gather(1, new_cell).unsqueeze(1).expand_as(pair_new)
        visit = visit_norm(self.visit_map.view(b, -1).gather(1, new_cell)).unsqueeze(1).expand_as(pair_new)
        flat.index_copy_(0, (pair_new + reading).view(-1), readings.reshape(-1))
        flat.index_copy_(0, (pair_new + visits).view(-1), visit.reshape(-1))

    def picture_maps(self, index: int) -> torch.Tensor:
        """The paper's 5 absolute maps of environment ``index`` (whatever the observation is)."""
        sl = slice(index, index + 1)
        maps = build_observations(self.positions[sl], self.reading_map[sl], self.visit_map[sl],
                                  self.walls_f[sl])
        return maps[0]

    def render_extras(self, index: int) -> dict[str, Any]:
        return {"target": tuple(int(v) for v in self.target[index].tolist())}

    def state(self, index: int) -> TargetLocalizationState:
        base = super().state(index)
        return TargetLocalizationState(
            step=base.step,
            positions=base.positions,
            mask=base.mask,
            target=tuple(int(v) for v in self.target[index].tolist()),
            walls=self.walls[index].clone(),
            readings=tuple(float(v) for v in self.readings[index].tolist()),
        )

    def oracle_action_scores(self) -> torch.Tensor:
        """float32 [B,N,A]: minus the BFS distance to the target after each move; -inf if invalid."""
        b, n = self.positions.shape[:2]
        idx = neighbour_index(self.positions, self.grid, self._deltas).view(b, -1)
        dist = self.dist_pad.view(b, -1).gather(1, idx).view(b, n, -1)
        return torch.where(self.mask, -dist, float("-inf"))


APPLICATION = register(Application(
    name=TargetLocalization.name,
    core=TargetLocalization,
    default_observation=DEFAULT_OBSERVATION,
    channels=observation_channels,
    action_names=ACTION_NAMES,
    has_estimate=True,
    sensing_presets=(DEFAULT_SENSING, *sorted(set(SENSING_PRESETS) - {DEFAULT_SENSING})),
    controllers=True,
    other_worlds=(("radbench", "medc_training.radbench.world:BenchWorld"),),
    observation_in_config=True,
    manifest_names_view=True,
))
