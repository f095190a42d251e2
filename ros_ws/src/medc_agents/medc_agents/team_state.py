"""What one agent knows about its team, built from messages, and its observation (no ROS here).

The agent keeps the same memory the training environment keeps (latest normalised reading and
visit count per cell, and the team's source posterior: ``medc_training.envs.tl_observation``
TeamMemory) and turns it into the observation its policy takes with the very builder the
environment uses (``tl_observation.observe`` and the grid module's move mask), so a policy sees in
ROS exactly what it saw in training. The memory holds everything any observation variant needs,
so a policy swap to a model that takes another variant keeps the episode's history.

Messages of one team step share one header stamp; an :class:`EpisodeStatus` names the step and
the walls map that holds. The agent decides once it has the status, the map, and every team
member's pose and reading for that stamp. Each check on a message raises ``ValueError`` with
the reason; the node logs it and drops the message.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from medc_sim.contract import agent_index, xy_to_cell

#: How many distinct stamps of poses/readings to keep while waiting for a status.
STAMP_HISTORY = 16


def stamp_key(stamp) -> int:
    """A builtin_interfaces/Time as integer nanoseconds (the key that ties a step together)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def walls_from_grid(msg, height: int, width: int) -> torch.Tensor:
    """bool [H,W] walls of a nav_msgs/OccupancyGrid (occupied = value >= 50).

    Raises:
        ValueError: dimensions differ from ``height`` x ``width`` or the data has the wrong size.
    """
    w, h = int(msg.info.width), int(msg.info.height)
    if (h, w) != (height, width):
        raise ValueError(f"map is {h}x{w}, this agent works on a {height}x{width} grid")
    cells = np.asarray(msg.data, dtype=np.int16)
    if cells.shape != (h * w,):
        raise ValueError(f"map data has {cells.size} cells, expected {h}x{w} = {h * w}")
    if cells.size and (cells.min() < -1 or cells.max() > 100):
        raise ValueError("map cells must be -1 (unknown), 0..100 (occupancy percent)")
    return torch.from_numpy(cells.reshape(h, w) >= 50)


def cell_from_pose(msg, resolution: float, height: int, width: int) -> tuple[int, int]:
    """Grid cell (row, col) of a geometry_msgs/PoseStamped in the map frame.

    Raises:
        ValueError: wrong frame, non-finite or off-grid position.
    """
    if msg.header.frame_id != "map":
        raise ValueError(f"pose in frame {msg.header.frame_id!r}, expected 'map'")
    return xy_to_cell(msg.pose.position.x, msg.pose.position.y, resolution, height, width)


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

    def __init__(self, agent_id: str, num_agents: int, grid: int, resolution: float = 1.0,
                 observation: str = "maps") -> None:
        from medc_training.envs.grid import action_deltas
        from medc_training.envs.target_localization import check_observation
        from medc_training.envs.tl_observation import ObservationSpec, TeamMemory

        self.agent_id = agent_id
        self.num_agents = num_agents
        self.index = agent_index(agent_id, num_agents)
        self.ids = [f"agent_{i}" for i in range(num_agents)]
        self.height = self.width = grid
        self.resolution = resolution
        self._deltas = action_deltas("cpu")
        self._positions: OrderedDict[int, list] = OrderedDict()
        self._readings: OrderedDict[int, list] = OrderedDict()
        self._maps: OrderedDict[int, torch.Tensor] = OrderedDict()
        self.pending: Tick | None = None
        # Memory of the episode being played, as in the environment.
        self.mem_episode = -1
        self.mem_step = -1
        #: The observation variant :meth:`observe` builds (set it when a policy swap needs another).
        self.observation = check_observation(observation, grid)
        self.memory = TeamMemory(ObservationSpec("maps", 0, True), 1, grid, "cpu")
        self._memory_started = False

    def use_observation(self, observation: str | None) -> None:
        """Build ``observation`` from now on (the memory keeps what every variant needs)."""
        from medc_training.envs.target_localization import check_observation

        if observation:
            self.observation = check_observation(observation, self.height)

    # -- inputs (each raises ValueError on bad input) ----------------------------------------
    def _slot(self, store: OrderedDict, key: int) -> list:
        if key not in store:
            store[key] = [None] * self.num_agents
            while len(store) > STAMP_HISTORY:
                store.popitem(last=False)
        return store[key]

    def add_map(self, msg) -> None:
        walls = walls_from_grid(msg, self.height, self.width)
        self._maps[stamp_key(msg.info.map_load_time)] = walls
        while len(self._maps) > 4:
            self._maps.popitem(last=False)

    def add_pose(self, agent_id: str, msg) -> None:
        idx = agent_index(agent_id, self.num_agents)
        cell = cell_from_pose(msg, self.resolution, self.height, self.width)
        self._slot(self._positions, stamp_key(msg.header.stamp))[idx] = cell

    def add_reading(self, agent_id: str, msg) -> None:
        idx = agent_index(agent_id, self.num_agents)
        value = value_from_reading(msg, agent_id)
        self._slot(self._readings, stamp_key(msg.header.stamp))[idx] = value

    def add_status(self, msg) -> Tick | None:
        """Take an EpisodeStatus; returns the tick to answer, or None (episode end / stale).

        Raises:
            ValueError: the status lists another team.
        """
        if list(msg.agent_ids) != self.ids:
            raise ValueError(f"status lists agents {list(msg.agent_ids)}, this team is {self.ids}")
        if msg.done:
            return None
        tick = Tick(int(msg.episode), int(msg.step), stamp_key(msg.header.stamp), stamp_key(msg.map_stamp))
        if (tick.episode, tick.step) < (self.mem_episode, self.mem_step):
            raise ValueError(
                f"status for episode {tick.episode} step {tick.step} is older than the one answered "
                f"(episode {self.mem_episode} step {self.mem_step})"
            )
        self.pending = tick
        return tick

    # -- decision ------------------------------------------------------------------------------
    def ready(self) -> bool:
        """The pending tick has everything it needs and has not been applied yet."""
        t = self.pending
        if t is None or (t.episode, t.step) == (self.mem_episode, self.mem_step):
            return False
        pos = self._positions.get(t.stamp)
        rd = self._readings.get(t.stamp)
        return (
            pos is not None
            and rd is not None
            and None not in pos
            and None not in rd
            and t.map_stamp in self._maps
        )

    def answered(self, episode: int, step: int) -> bool:
        """This agent already observed (and so decided) (episode, step)."""
        return (episode, step) == (self.mem_episode, self.mem_step)

    def observe(self) -> tuple[torch.Tensor, torch.Tensor, Tick]:
        """Apply the pending tick to the memory; returns (obs [C,H,W], mask [A], tick).

        Call only when :meth:`ready` is True.
        """
        from medc_training.envs.grid import move_mask, pad_blocked
        from medc_training.envs.tl_observation import observe

        t = self.pending
        assert t is not None and self.ready()
        positions = torch.tensor([self._positions[t.stamp]], dtype=torch.long)  # [1,N,2]
        readings = torch.tensor([self._readings[t.stamp]], dtype=torch.float32)  # [1,N]
        walls = self._maps[t.map_stamp].unsqueeze(0)
        if t.episode != self.mem_episode or not self._memory_started:
            self.memory.start(walls, positions, readings)
            self._memory_started = True
        else:
            self.memory.record(walls, positions, readings)
        self.mem_episode, self.mem_step = t.episode, t.step
        m = self.memory
        estimate = m.estimate_map() if self.observation.estimate else None
        obs = observe(self.observation, positions, m.reading_map, m.visit_map, walls.float(), estimate)
        obs = obs[0, self.index]
        mask = move_mask(positions, pad_blocked(walls), self._deltas)[0, self.index]
        # Free what this step used; older stamps can never be answered again.
        for store in (self._positions, self._readings):
            for key in [k for k in store if k <= t.stamp]:
                del store[key]
        return obs, mask, t
