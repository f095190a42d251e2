"""What one agent knows about its team, built from messages, and its observation (no ROS here).

The agent keeps the same memory the training environment keeps (latest normalised reading and
visit count per cell, and the team's source posterior: ``medc_training.envs.tl_observation``
TeamMemory) and turns it into the observation its policy takes with the very builder the
environment uses (``tl_observation.observe`` and the grid module's move mask), so a policy sees in
ROS exactly what it saw in training. The memory holds everything any observation variant needs,
so a policy swap to a model that takes another variant keeps the episode's history.

Messages of one team step share one header stamp; an :class:`EpisodeStatus` names the step and
the walls map that holds (its ``info.map_load_time``). The agent decides once it has the status,
the map, and every team member's pose and reading for that stamp. Poses are in the ``map`` frame
(REP 103: x east, y north) and are turned into cells with the grid geometry of the map
(``info.origin``, ``info.resolution``; ``medc_common.contract.GridGeometry``). Each check on a
message raises ``ValueError`` with the reason; the node logs it and drops the message.
:meth:`TeamObserver.waiting_for` says what a step still lacks, for the node's stall report.

Episodes (docs/ros.md, "Episodes and restarts"): a status starts a new episode (the memory is
reset) when its ``step`` is 0 (and it is not a re-send of the step-0 status already answered:
same stamp), or its ``episode`` or ``map_stamp`` differs from the episode in memory. So a driver
that restarts (episode 0 step 0 again, a new map) is followed at once. Within one episode on one
map a status for an older step is dropped, and one for the step already answered is a re-send.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from medc_common.contract import (
    MAP_FRAME,
    OCCUPIED_THRESHOLD,
    GridGeometry,
    agent_ids,
    agent_index,
    geometry_of,
    occupancy_to_walls,
)

#: How many distinct stamps of poses/readings to keep while waiting for a status.
STAMP_HISTORY = 16
#: Default edge tolerance (cells): a pose at most this far outside the grid snaps to the edge cell.
EDGE_TOLERANCE_CELLS = 0.5


def stamp_key(stamp) -> int:
    """A builtin_interfaces/Time as integer nanoseconds (the key that ties a step together)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def walls_from_grid(msg, height: int, width: int) -> torch.Tensor:
    """bool [H,W] walls (environment rows, row 0 = north) of a nav_msgs/OccupancyGrid: a cell is a
    wall when its value is >= 50 (contract.OCCUPIED_THRESHOLD); 0..49 and -1 (unknown) are free.
    Message row j is environment row H - 1 - j (contract.occupancy_to_walls).

    Raises:
        ValueError: another frame, dimensions differ from ``height`` x ``width``, the data has the
        wrong size or values outside -1..100.
    """
    if msg.header.frame_id != MAP_FRAME:
        raise ValueError(f"map in frame {msg.header.frame_id!r}, expected {MAP_FRAME!r}")
    w, h = int(msg.info.width), int(msg.info.height)
    if (h, w) != (height, width):
        raise ValueError(f"map is {h}x{w}, this agent works on a {height}x{width} grid")
    cells = np.asarray(msg.data, dtype=np.int16)
    if cells.shape != (h * w,):
        raise ValueError(f"map data has {cells.size} cells, expected {h}x{w} = {h * w}")
    if cells.size and (cells.min() < -1 or cells.max() > 100):
        raise ValueError("map cells must be -1 (unknown), 0..100 (occupancy percent)")
    return torch.from_numpy(occupancy_to_walls(cells, h, w))


def check_wall_segments(walls: torch.Tensor, most: int) -> None:
    """Check that bool ``walls`` [H,W] are at most ``most`` straight wall segments, one cell thick,
    that the realistic sensing model's exact line-of-sight rule can take as one rectangle each
    (``tl_sensing.wall_rectangles``: a segment starts at a wall cell with no wall above or to its
    left and runs right or down), as the environment places them (segments that never touch).

    Raises:
        ValueError: more segments, or wall cells that are not such segments (an L, a T, a block).
    """
    from medc_training.envs.tl_sensing import wall_rectangles

    rects = wall_rectangles(walls.unsqueeze(0), walls.numel())[0]
    rects = rects[rects[:, 2] > rects[:, 0]]
    if len(rects) > most:
        raise ValueError(f"map has {len(rects)} wall segments; this agent's grid takes at most {most}")
    h, w = walls.shape
    rows = torch.arange(h, dtype=torch.float32).view(1, h, 1)
    cols = torch.arange(w, dtype=torch.float32).view(1, 1, w)
    r = rects.view(-1, 4, 1, 1)
    covered = ((rows > r[:, 0]) & (rows < r[:, 2]) & (cols > r[:, 1]) & (cols < r[:, 3])).sum(0)
    if bool((covered != walls.to(covered.dtype)).any()):
        raise ValueError("map walls must be straight segments one cell thick that do not touch each other "
                         "(an L, a T or a block is not): the realistic sensing model's line of sight "
                         "takes each as one rectangle")


def faint_cells(msg) -> int:
    """How many cells of an OccupancyGrid hold 1..49: free by the contract's threshold, but maybe
    walls a driver meant (e.g. published as 1)."""
    cells = np.asarray(msg.data, dtype=np.int16)
    return int(((cells > 0) & (cells < OCCUPIED_THRESHOLD)).sum())


def xy_from_pose(msg) -> tuple[float, float]:
    """Map-frame (x, y) of a geometry_msgs/PoseStamped (z and orientation are ignored).

    Raises:
        ValueError: wrong frame or non-finite position.
    """
    if msg.header.frame_id != MAP_FRAME:
        raise ValueError(f"pose in frame {msg.header.frame_id!r}, expected {MAP_FRAME!r}")
    x, y = float(msg.pose.position.x), float(msg.pose.position.y)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"position ({x}, {y}) is not finite")
    return x, y


def show_stamp(key: int) -> str:
    """A stamp key (integer ns) as ``sec.nanosec`` seconds."""
    return f"{key // 1_000_000_000}.{key % 1_000_000_000:09d}"


def value_from_reading(msg, expected_agent: str) -> float:
    """The raw value of a medc_interfaces/RadiationReading published on ``expected_agent``'s topic.

    Raises:
        ValueError: the message names another agent, or the value/variance is not a finite
        non-negative number.
    """
    if msg.agent_id != expected_agent:
        raise ValueError(f"reading on {expected_agent}'s topic names agent {msg.agent_id!r}")
    if not math.isfinite(msg.value) or msg.value < 0:
        raise ValueError(f"reading {msg.value} from {expected_agent} is not a finite non-negative number")
    if not math.isfinite(msg.variance) or msg.variance < 0:
        raise ValueError(f"reading variance {msg.variance} from {expected_agent} is invalid")
    return float(msg.value)


@dataclass(frozen=True)
class Tick:
    """One team step the agent must answer."""

    episode: int
    step: int
    stamp: int
    map_stamp: int


class TeamObserver:
    """Collects the team's poses, readings and map, and builds this agent's observation."""

    def __init__(self, agent_id: str, num_agents: int, grid: int, resolution: float = 0.0,
                 observation: str = "maps", sensing: str = "paper-simple", rule_out: bool = True,
                 edge_tolerance: float = EDGE_TOLERANCE_CELLS) -> None:
        """``resolution``: metres per cell the maps must have; 0 = whatever the map says.
        ``edge_tolerance``: cells; a pose at most this far outside the grid's edge is taken as the
        nearest edge cell (GNSS noise on the edge row), one farther out is dropped with the distance.
        ``sensing``: the team's sensing preset (``medc_training.envs.tl_sensing.SENSING_PRESETS``),
        which the readings follow; the memory normalises them and weighs the source posterior by it.
        ``rule_out``: the driver ends an episode as soon as an agent finds the source, so the cells
        the team stood on without the episode ending are not the source (False: a driver that ends
        episodes only on the team's declaration; ``SourceEstimator``'s ``rule_out``).
        ``grid``: the grid the agent starts on. An observation that does not depend on the grid's
        size (an agent-centred window, ``egoR``) takes a square map of any size, and the memory
        follows the map of each episode; the whole-grid ``maps`` observation takes ``grid`` only.

        Raises:
            ValueError: an unknown sensing preset.
        """
        from medc_training.envs.grid import action_deltas
        from medc_training.envs.tl_observation import parse_observation
        from medc_training.envs.tl_sensing import parse_sensing

        self.agent_id = agent_id
        self.num_agents = num_agents
        self.index = agent_index(agent_id, num_agents)
        self.ids = agent_ids(num_agents)
        self.height = self.width = grid
        self.resolution = float(resolution)
        self._deltas = action_deltas("cpu")
        # Per stamp: raw map-frame (x, y) of each agent, and its reading.
        self._positions: OrderedDict[int, list] = OrderedDict()
        self._readings: OrderedDict[int, list] = OrderedDict()
        #: map_load_time key -> (walls [H,W], geometry, header stamp key)
        self._maps: OrderedDict[int, tuple[torch.Tensor, GridGeometry, int]] = OrderedDict()
        self._geometry: GridGeometry | None = None  # of the latest map
        self.pending: Tick | None = None
        self.edge_tolerance = max(0.0, float(edge_tolerance))
        #: Teammates taken out of the team (docs/ros.md, "A lost UAV"): steps are decided without
        #: their pose and reading; their last cell stays in the observation.
        self.absent: set[int] = set()
        self._last_cells: list[tuple[int, int] | None] = [None] * num_agents
        self._last_xy: list[tuple[float, float] | None] = [None] * num_agents
        self._force_start = False
        # Memory of the episode being played, as in the environment.
        self.mem_episode = -1
        self.mem_step = -1
        self.mem_stamp = -1
        self.mem_map = -1
        #: For the stall report: latest stamp received and latest drop reason, per (kind, agent).
        self.latest: dict[tuple[str, int], int] = {}
        self.last_drop: dict[tuple[str, int], str] = {}
        #: Why the last map was dropped (for the stall report), if one was.
        self.last_map_drop = ""
        #: Things worth one log line each (a restarted driver, a suspicious map); the node drains it.
        self.notes: list[str] = []
        #: The observation variant :meth:`observe` builds (set it when a policy swap needs another).
        self.observation = parse_observation(observation)
        self.sensing = parse_sensing(sensing)
        self.rule_out = bool(rule_out)
        self._resize(grid)
        self._memory_started = False
        #: The last observed step (:meth:`observe`): every agent's cell int64 [1,N,2], the walls
        #: bool [1,G,G] and every agent's move mask bool [1,N,A]; what a controller decides from.
        self.positions: torch.Tensor | None = None
        self.walls: torch.Tensor | None = None
        self.team_mask: torch.Tensor | None = None

    def _resize(self, grid: int) -> None:
        """Work on a ``grid``×``grid`` area from now on: a fresh memory of that size."""
        from medc_training.envs.target_localization import max_walls
        from medc_training.envs.tl_observation import ObservationSpec, TeamMemory

        self.height = self.width = int(grid)
        #: Most wall segments a map may hold (the exact line-of-sight rule keeps one rectangle
        #: each): as many as the environment places on this grid.
        self.max_walls = max(1, max_walls(grid))
        self.memory = TeamMemory(ObservationSpec("maps", 0, True), 1, grid, "cpu", sensing=self.sensing,
                                 max_walls=self.max_walls, rule_out=self.rule_out)

    @property
    def any_grid(self) -> bool:
        """Whether the observation built does not depend on the grid's size (an agent-centred
        window), so that a map of any square size can be played."""
        return self.observation.view != "maps"

    def map_geometry(self, map_stamp: int) -> GridGeometry | None:
        """The grid geometry of the map with ``info.map_load_time`` ``map_stamp`` (a stamp key), if held."""
        entry = self._maps.get(map_stamp)
        return None if entry is None else entry[1]

    def use_observation(self, observation: str | None) -> None:
        """Build ``observation`` from now on (the memory keeps what every variant needs)."""
        from medc_training.envs.tl_observation import parse_observation

        if observation:
            self.observation = parse_observation(observation)

    # -- inputs (each raises ValueError on bad input) ----------------------------------------
    def _slot(self, store: OrderedDict, key: int) -> list:
        if key not in store:
            store[key] = [None] * self.num_agents
            while len(store) > STAMP_HISTORY:
                store.popitem(last=False)
        return store[key]

    def add_map(self, msg) -> None:
        try:
            from medc_training.envs.target_localization import max_walls

            size = (int(msg.info.height), int(msg.info.width))
            if size != (self.height, self.width) and self.any_grid:
                from medc_training.bundle import MAX_BUNDLE_GRID

                if size[0] != size[1] or not 5 <= size[0] <= MAX_BUNDLE_GRID:
                    raise ValueError(f"map is {size[0]}x{size[1]}: the team works on square grids of 5x5 to "
                                     f"{MAX_BUNDLE_GRID}x{MAX_BUNDLE_GRID} cells")
                height = width = size[0]
            elif size != (self.height, self.width):
                raise ValueError(f"map is {size[0]}x{size[1]}, but this agent's observation "
                                 f"'{self.observation.name}' shows the whole {self.height}x{self.width} "
                                 "grid its policy was trained on: publish a map of that size, or run a "
                                 "policy with an agent-centred observation (egoR), which plays any size")
            else:
                height, width = self.height, self.width
            walls = walls_from_grid(msg, height, width)
            if self.sensing.line == "exact":
                check_wall_segments(walls, max(1, max_walls(height)))
            geometry = geometry_of(msg)
            if self.resolution > 0 and abs(geometry.resolution - self.resolution) > 1e-9 * self.resolution:
                raise ValueError(f"map resolution is {geometry.resolution:g} m, this agent's 'resolution' "
                                 f"parameter is {self.resolution:g} m")
        except ValueError as exc:
            load = show_stamp(stamp_key(msg.info.map_load_time))
            self.last_map_drop = f"map with map_load_time {load}: {exc}"
            raise
        faint = faint_cells(msg)
        if faint:
            self.notes.append(
                f"map with map_load_time {show_stamp(stamp_key(msg.info.map_load_time))} has {faint} cells "
                f"valued 1..{OCCUPIED_THRESHOLD - 1}: they are free; a wall is >= {OCCUPIED_THRESHOLD} "
                "(publish 100 for a wall, 0 for free)")
        key = stamp_key(msg.info.map_load_time)
        self._maps[key] = (walls, geometry, stamp_key(msg.header.stamp))
        self._maps.move_to_end(key)
        self._geometry = geometry
        # Keep the last 4 maps, but never the one the episode in play or the pending step uses: a
        # burst of other maps cannot take the team's map away (issue 20).
        keep = {self.mem_map, self.pending.map_stamp if self.pending is not None else None}
        for old in [k for k in self._maps if k not in keep][:max(0, len(self._maps) - 4)]:
            del self._maps[old]

    def map_entry(self, key: int) -> tuple[torch.Tensor, GridGeometry, int] | None:
        """(walls, geometry, header stamp) of the map with ``info.map_load_time`` ``key``, if held."""
        return self._maps.get(key)

    def episode_geometry(self) -> GridGeometry | None:
        """The grid of the map the pending step (else the episode in memory) names, if received;
        before any status, the latest map's."""
        for key in (self.pending.map_stamp if self.pending is not None else None, self.mem_map):
            if key in self._maps:
                return self._maps[key][1]
        return self._geometry if self.pending is None and self.mem_step < 0 else None

    def tolerance_m(self, geometry: GridGeometry) -> float:
        """The edge tolerance in metres on ``geometry``'s grid."""
        return self.edge_tolerance * geometry.resolution

    def latest_xy(self) -> list[tuple[float, float]]:
        """Each agent's latest pose received (raw map-frame x, y), for those heard from."""
        return [xy for xy in self._last_xy if xy is not None]

    def restart(self) -> None:
        """Take the next step as the start of an episode in memory (the agent follows the driver
        again after answering a step that was not the driver's)."""
        self.mem_step = -1
        self._force_start = True

    def _record_drop(self, kind: str, idx: int, exc: ValueError) -> None:
        self.last_drop[(kind, idx)] = str(exc)

    def index_of(self, agent_id: str) -> int:
        """The team index of ``agent_id``."""
        return agent_index(agent_id, self.num_agents)

    def add_pose(self, agent_id: str, msg) -> None:
        idx = agent_index(agent_id, self.num_agents)
        try:
            xy = xy_from_pose(msg)
            geometry = self.episode_geometry()
            if geometry is not None:  # off the grid of the episode's map: drop it now
                geometry.xy_to_cell(*xy, self.tolerance_m(geometry))
        except ValueError as exc:
            self._record_drop("pose", idx, exc)
            raise ValueError(f"pose of {agent_id}: {exc}") from None
        key = stamp_key(msg.header.stamp)
        self._slot(self._positions, key)[idx] = xy
        self._last_xy[idx] = xy
        self.latest[("pose", idx)] = key

    def add_reading(self, agent_id: str, msg) -> None:
        idx = agent_index(agent_id, self.num_agents)
        try:
            value = value_from_reading(msg, agent_id)
        except ValueError as exc:
            self._record_drop("reading", idx, exc)
            raise ValueError(f"reading on {agent_id}'s topic: {exc}") from None
        key = stamp_key(msg.header.stamp)
        self._slot(self._readings, key)[idx] = value
        self.latest[("reading", idx)] = key

    def add_status(self, msg) -> Tick | None:
        """Take an EpisodeStatus; returns the tick to answer, or None (episode end).

        The returned tick may be one already answered (:meth:`answered_tick`): a re-sent step.

        Raises:
            ValueError: the status lists another team, or is for an older step of the episode
            being played (same episode and map, a lower step other than 0).
        """
        if list(msg.agent_ids) != self.ids:
            raise ValueError(f"status lists agents {list(msg.agent_ids)}, this team is {self.ids}")
        if msg.done:
            return None
        tick = Tick(int(msg.episode), int(msg.step), stamp_key(msg.header.stamp), stamp_key(msg.map_stamp))
        same_episode = (tick.episode, tick.map_stamp) == (self.mem_episode, self.mem_map)
        if same_episode and 0 < tick.step < self.mem_step:
            raise ValueError(
                f"status for episode {tick.episode} step {tick.step} is older than the one answered "
                f"(episode {self.mem_episode} step {self.mem_step}, same map)"
            )
        if not self.answered_tick(tick):
            self.pending = tick
        return tick

    # -- decision ------------------------------------------------------------------------------
    def answered_tick(self, t: Tick) -> bool:
        """``t`` is the step already observed (and so decided): same episode, map and step (and,
        for step 0, the same stamp: a step 0 with a new stamp is a new start)."""
        same = (t.episode, t.map_stamp, t.step) == (self.mem_episode, self.mem_map, self.mem_step)
        return same and (t.step != 0 or t.stamp == self.mem_stamp)

    def _cells(self, t: Tick) -> list[tuple[int, int]] | None:
        """Every agent's cell at ``t``; an absent teammate without a pose at ``t`` keeps its last
        cell (this agent's own when it has none)."""
        xys = self._positions.get(t.stamp)
        entry = self._maps.get(t.map_stamp)
        if xys is None or entry is None or xys[self.index] is None:
            return None
        geometry = entry[1]
        cells = []
        try:
            for j, xy in enumerate(xys):
                if xy is None and j not in self.absent:
                    return None
                cells.append(None if xy is None else geometry.xy_to_cell(*xy, self.tolerance_m(geometry)))
        except ValueError:
            return None
        own = cells[self.index]
        return [c if c is not None else (self._last_cells[j] or own) for j, c in enumerate(cells)]

    def present(self, t: Tick) -> list[int]:
        """The agents whose pose and reading at ``t`` are both here."""
        xys = self._positions.get(t.stamp) or [None] * self.num_agents
        rd = self._readings.get(t.stamp) or [None] * self.num_agents
        return [j for j in range(self.num_agents) if xys[j] is not None and rd[j] is not None]

    def missing(self) -> dict[int, list[str]]:
        """For the pending tick: agent index -> kinds ('pose', 'reading') still missing."""
        t = self.pending
        if t is None or self.answered_tick(t):
            return {}
        out: dict[int, list[str]] = {}
        for kind, store in (("pose", self._positions), ("reading", self._readings)):
            got = store.get(t.stamp) or [None] * self.num_agents
            for j, value in enumerate(got):
                if value is None:
                    out.setdefault(j, []).append(kind)
        return out

    def ready(self) -> bool:
        """The pending tick has everything it needs and has not been applied yet."""
        t = self.pending
        if t is None or self.answered_tick(t):
            return False
        rd = self._readings.get(t.stamp)
        if rd is None or any(v is None and j not in self.absent for j, v in enumerate(rd)):
            return False
        return self._cells(t) is not None

    def waiting_for(self) -> tuple[list[str], list[str]]:
        """(what the pending tick still lacks, what the agent has instead), as sentences."""
        t = self.pending
        if t is None or self.answered_tick(t):
            return [], []
        need, have = [], []
        if t.map_stamp not in self._maps:
            need.append(f"the map with info.map_load_time {show_stamp(t.map_stamp)} "
                        "(the status's map_stamp)")
            if self._maps:
                loads = ", ".join(show_stamp(k) for k in self._maps)
                have.append(f"maps with info.map_load_time {loads}")
                for load, (_, _, header) in self._maps.items():
                    if header == t.map_stamp and load != t.map_stamp:
                        have.append(f"the map whose header.stamp is {show_stamp(header)} has "
                                    f"info.map_load_time {show_stamp(load)}: map_stamp must equal "
                                    "info.map_load_time")
            elif self.last_map_drop:
                have.append(f"no usable map: the last one was dropped ({self.last_map_drop})")
            else:
                have.append("no map on the map topic")
        for kind, store in (("pose", self._positions), ("reading", self._readings)):
            got = store.get(t.stamp) or [None] * self.num_agents
            for j, value in enumerate(got):
                if value is not None or j in self.absent:
                    continue
                need.append(f"the {kind} of {self.ids[j]} stamped {show_stamp(t.stamp)}")
                latest = self.latest.get((kind, j))
                if latest is None:
                    have.append(f"no {kind} of {self.ids[j]} yet")
                else:
                    off = (latest - t.stamp) / 1000.0
                    have.append(f"latest {kind} of {self.ids[j]} stamped {show_stamp(latest)} "
                                f"({off:+.3f} us from the status)")
                if (kind, j) in self.last_drop:
                    have.append(f"last {kind} of {self.ids[j]} dropped: {self.last_drop[(kind, j)]}")
        entry = self._maps.get(t.map_stamp)
        xys = self._positions.get(t.stamp)
        if entry is not None and xys is not None:
            for j, xy in enumerate(xys):
                if xy is None:
                    continue
                try:
                    entry[1].xy_to_cell(*xy, self.tolerance_m(entry[1]))
                except ValueError as exc:
                    need.append(f"a pose of {self.ids[j]} on the map")
                    have.append(f"{self.ids[j]}: {exc}")
        return need, have

    def orphan_round(self) -> int | None:
        """The stamp of a complete round of poses and readings newer than the last answered step
        for which no status came, if any (a driver that forgot the status, or stamped it apart)."""
        for key in reversed(self._positions):
            if key <= self.mem_stamp and self.mem_stamp >= 0:
                continue
            rd = self._readings.get(key)
            complete = None not in self._positions[key] and rd is not None and None not in rd
            if complete and (self.pending is None or self.pending.stamp != key):
                return key
        return None

    def observe(self) -> tuple[torch.Tensor, torch.Tensor, Tick]:
        """Apply the pending tick to the memory; returns (obs [C,H,W], mask [A], tick).

        Call only when :meth:`ready` is True.
        """
        from medc_training.envs.grid import move_mask, pad_blocked
        from medc_training.envs.tl_observation import observe

        t = self.pending
        assert t is not None and self.ready()
        cells = self._cells(t)
        positions = torch.tensor([cells], dtype=torch.long)  # [1,N,2]
        readings = torch.tensor([[0.0 if v is None else v for v in self._readings[t.stamp]]],
                                dtype=torch.float32)  # [1,N]
        walls = self._maps[t.map_stamp][0].unsqueeze(0)
        here = self.present(t)
        for j in here:
            self._last_cells[j] = cells[j]
        if len(here) < self.num_agents:  # a teammate taken out: record only the readings that came
            sensed_pos, sensed = positions[:, here], readings[:, here]
        else:
            sensed_pos, sensed = positions, readings
        new_episode = (t.episode, t.map_stamp) != (self.mem_episode, self.mem_map) or t.step == 0
        if self._force_start:
            new_episode, self._force_start = True, False
            self._memory_started = False
        if new_episode or not self._memory_started:
            if walls.shape[-1] != self.memory.grid:
                self._resize(walls.shape[-1])
            if self._memory_started and (t.episode, t.step) <= (self.mem_episode, self.mem_step):
                self.notes.append(
                    f"episode status went back from episode {self.mem_episode} step {self.mem_step} to "
                    f"episode {t.episode} step {t.step} (map_load_time {show_stamp(self.mem_map)} -> "
                    f"{show_stamp(t.map_stamp)}): the driver restarted; memory reset, following it")
            self.memory.start(walls, sensed_pos, sensed)
            self._memory_started = True
        else:
            self.memory.record(walls, sensed_pos, sensed)
        self.mem_episode, self.mem_step = t.episode, t.step
        self.mem_stamp, self.mem_map = t.stamp, t.map_stamp
        m = self.memory
        estimate = m.estimate_map() if self.observation.estimate else None
        obs = observe(self.observation, positions, m.reading_map, m.visit_map, walls.float(), estimate)
        obs = obs[0, self.index]
        team_mask = move_mask(positions, pad_blocked(walls), self._deltas)
        mask = team_mask[0, self.index]
        self.positions, self.walls, self.team_mask = positions, walls, team_mask
        # Free what this step used; older stamps can never be answered again.
        for store in (self._positions, self._readings):
            for key in [k for k in store if k <= t.stamp]:
                del store[key]
        return obs, mask, t
