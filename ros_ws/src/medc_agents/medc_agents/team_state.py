"""What one agent knows about its team, built from messages, and its observation (no ROS here).

:class:`TeamObserver` takes the team's messages and answers one step at a time; each job is its own
unit, tested on its own:

- :mod:`medc_agents.team_messages`: the checks on each message (stamps, poses in the ``map`` frame,
  readings, walls maps); a bad message raises ``ValueError`` with the reason, and the node logs it
  and drops the message;
- :class:`~medc_agents.team_episode.EpisodeClock`: which step is answered next, from the episode
  statuses, and when the memory starts afresh (docs/ros-reference.md, "Episodes and restarts");
- :class:`~medc_agents.team_inputs.MapStore` and :class:`~medc_agents.team_inputs.TeamRounds`: the
  maps and the poses and readings held until a step is answered, and what a step still lacks
  (:meth:`TeamObserver.waiting_for`, for the node's stall report);
- :class:`~medc_agents.team_memory.AgentMemory`: the training environment's team memory (readings,
  visits, the source posterior) and the observation built from it, bit for bit as in training.

Messages of one team step share one header stamp; an ``EpisodeStatus`` names the step and the
walls map that holds (its ``info.map_load_time``). The agent decides once it has the status, the
map, and every team member's pose and reading for that stamp.
"""

from __future__ import annotations

import torch
from medc_common.contract import OCCUPIED_THRESHOLD, GridGeometry, agent_ids, agent_index

from medc_agents.team_episode import EpisodeClock, Tick
from medc_agents.team_inputs import MapStore, TeamRounds
from medc_agents.team_memory import AgentMemory
from medc_agents.team_messages import (
    EDGE_TOLERANCE_CELLS,
    faint_cells,
    map_from_message,
    pose_refusals,
    show_stamp,
    stamp_key,
    value_from_reading,
    xy_from_pose,
)


class TeamObserver:
    """Collects the team's poses, readings and map, and builds this agent's observation."""

    def __init__(self, agent_id: str, num_agents: int, grid: int, resolution: float = 0.0,
                 observation: str = "maps", sensing: str = "paper-simple", rule_out: bool = True,
                 edge_tolerance: float = EDGE_TOLERANCE_CELLS, world: str = "grid") -> None:
        """``resolution``: metres per cell the maps must have (0: any). ``edge_tolerance``: cells
        outside the grid a pose may lie and be taken as the nearest edge cell. ``sensing``: the
        team's sensing preset (ValueError for an unknown one). ``rule_out``: the driver ends an
        episode when an agent finds the source, so cells stood on are not it. ``grid``: the
        starting grid; an ``egoR`` observation follows each episode's square map, ``maps`` takes
        ``grid`` only. ``world``: ``grid`` (maps of wall segments) or ``radbench`` (the field
        benchmark's: maps of solid obstructions; ``sensing`` is then its team model,
        ``medc_agents.bench_team.team_model``)."""
        from medc_training.envs.observation import parse_observation
        from medc_training.envs.tl_sensing import parse_sensing

        from medc_agents.bench_team import check_world

        self.agent_id = agent_id
        self.num_agents = num_agents
        self.index = agent_index(agent_id, num_agents)
        self.ids = agent_ids(num_agents)
        self.resolution = float(resolution)
        self.edge_tolerance = max(0.0, float(edge_tolerance))
        #: Things worth one log line each (a restarted driver, a suspicious map); the node drains it.
        self.notes: list[str] = []
        #: Poses held unchecked and dropped once their step's map was known (the node logs and counts them).
        self.late_drops: list[str] = []
        #: The observation variant :meth:`observe` builds (set it when a policy swap needs another).
        self.observation = parse_observation(observation)
        self.sensing = parse_sensing(sensing)
        self.rule_out = bool(rule_out)
        self.world = check_world(world)
        #: The step answered and the one pending.
        self.clock = EpisodeClock()
        #: The maps held, and the poses and readings held (who is absent included).
        self.maps = MapStore()
        self.rounds = TeamRounds(num_agents)
        #: The team memory and the last observed step.
        self.team = AgentMemory(grid, self.sensing, self.rule_out, self.world)

    # -- what the units hold, under the names the controllers and tests read ------------------
    @property
    def memory(self):
        """The team memory (``tl_observation.TeamMemory``) of the episode in play."""
        return self.team.memory

    @property
    def max_walls(self) -> int:
        """Most wall segments a map may hold on the current grid."""
        return self.team.max_walls

    @property
    def height(self) -> int:
        """Rows (= columns) of the grid the agent works on now."""
        return self.team.grid

    @property
    def positions(self) -> torch.Tensor | None:
        """Every agent's cell int64 [1,N,2] at the last observed step."""
        return self.team.positions

    @property
    def walls(self) -> torch.Tensor | None:
        """The walls bool [1,G,G] of the last observed step."""
        return self.team.walls

    @property
    def team_mask(self) -> torch.Tensor | None:
        """Every agent's move mask bool [1,N,A] at the last observed step."""
        return self.team.team_mask

    @property
    def absent(self) -> set[int]:
        """Teammates taken out of the team (docs/ros-reference.md, "A lost UAV")."""
        return self.rounds.absent

    @property
    def any_grid(self) -> bool:
        """Whether the observation built does not depend on the grid's size (an agent-centred
        window), so that a map of any square size can be played."""
        return self.observation.view != "maps"

    def use_observation(self, observation: str | None) -> None:
        """Build ``observation`` from now on (the memory keeps what every variant needs)."""
        from medc_training.envs.observation import parse_observation

        if observation:
            self.observation = parse_observation(observation)

    def index_of(self, agent_id: str) -> int:
        """The team index of ``agent_id``."""
        return agent_index(agent_id, self.num_agents)

    def map_geometry(self, map_stamp: int) -> GridGeometry | None:
        """The grid geometry of the map with ``info.map_load_time`` ``map_stamp`` (a stamp key), if held."""
        return self.maps.geometry(map_stamp)

    def episode_geometry(self) -> GridGeometry | None:
        """The grid of the map the pending step (else the episode in memory) names, if received;
        before any status, the latest map's."""
        for key in self.clock.maps_in_use():
            if key in self.maps:
                return self.maps.geometry(key)
        return self.maps.latest if self.clock.pending is None and self.clock.step < 0 else None

    def tolerance_m(self, geometry: GridGeometry) -> float:
        """The edge tolerance in metres on ``geometry``'s grid."""
        return self.edge_tolerance * geometry.resolution

    # -- inputs (each raises ValueError on bad input) ----------------------------------------
    def add_map(self, msg) -> None:
        load = stamp_key(msg.info.map_load_time)
        try:
            walls, geometry = map_from_message(msg, self.height, self.any_grid, self.observation.name,
                                               self.sensing.line == "exact", self.resolution,
                                               obstructions=self.world == "radbench")
        except ValueError as exc:
            self.maps.refuse(load, str(exc))
            raise
        faint = faint_cells(msg)
        if faint:
            self.notes.append(
                f"map with map_load_time {show_stamp(load)} has {faint} cells "
                f"valued 1..{OCCUPIED_THRESHOLD - 1}: they are free; a wall is >= {OCCUPIED_THRESHOLD} "
                "(publish 100 for a wall, 0 for free)")
        self.maps.put(load, walls, geometry, stamp_key(msg.header.stamp), keep=self.clock.maps_in_use())

    def add_pose(self, agent_id: str, msg) -> None:
        """Hold a pose. It is checked against the map of its step: the pending step's when its status
        came first; else the episode's or the latest map received (a new episode's, which comes
        before its first poses). A pose on none of them whose step is not known yet is held
        unchecked (its area's map may be on its way) and checked once its status names the map
        (:meth:`ready`), unless a pose of that agent and stamp already lies on a map."""
        idx = agent_index(agent_id, self.num_agents)
        key = stamp_key(msg.header.stamp)
        verified = True
        try:
            xy = xy_from_pose(msg)
            t = self.clock.pending
            if t is not None and t.stamp == key:
                geometries = [self.maps.geometry(t.map_stamp)]
            else:
                geometries = [self.episode_geometry(), self.maps.latest]
            errors = pose_refusals(xy, [g for g in geometries if g is not None], self.edge_tolerance)
            if errors is not None:
                if errors and ((t is not None and t.stamp == key) or self.rounds.has_verified_pose(idx, key)):
                    raise errors[0]
                verified = False
        except ValueError as exc:
            self.rounds.drop("pose", idx, str(exc))
            raise ValueError(f"pose of {agent_id}: {exc}") from None
        self.rounds.add("pose", idx, key, xy, verified)

    def add_reading(self, agent_id: str, msg) -> None:
        idx = agent_index(agent_id, self.num_agents)
        try:
            value = value_from_reading(msg, agent_id)
        except ValueError as exc:
            self.rounds.drop("reading", idx, str(exc))
            raise ValueError(f"reading on {agent_id}'s topic: {exc}") from None
        self.rounds.add("reading", idx, stamp_key(msg.header.stamp), value)

    def add_status(self, msg) -> Tick | None:
        """Take an EpisodeStatus; returns the tick to answer, or None (episode end); see
        :meth:`EpisodeClock.take_status <medc_agents.team_episode.EpisodeClock.take_status>`."""
        return self.clock.take_status(msg, self.ids)

    def restart(self) -> None:
        """Take the next step as the start of an episode in memory."""
        self.clock.restart()

    # -- decision ------------------------------------------------------------------------------
    def answered_tick(self, t: Tick) -> bool:
        """``t`` is the step already observed (and so decided)."""
        return self.clock.answered(t)

    def _cells(self, t: Tick) -> list[tuple[int, int]] | None:
        geometry = self.maps.geometry(t.map_stamp)
        if geometry is None:
            return None
        return self.rounds.cells(t.stamp, geometry, self.tolerance_m(geometry), self.index)

    def missing(self) -> dict[int, list[str]]:
        """For the pending tick: agent index -> kinds ('pose', 'reading') still missing."""
        t = self.clock.open_tick()
        return {} if t is None else self.rounds.missing(t.stamp)

    def ready(self) -> bool:
        """The pending tick has everything it needs and has not been applied yet (poses held
        unchecked are checked against its map first: :attr:`late_drops` lists those dropped)."""
        t = self.clock.open_tick()
        if t is None:
            return False
        geometry = self.maps.geometry(t.map_stamp)
        if geometry is not None and self.rounds.unverified:
            for idx, reason in self.rounds.verify(t.stamp, geometry, self.tolerance_m(geometry)):
                self.late_drops.append(f"pose of {self.ids[idx]}: {reason}")
        return self.rounds.readings_complete(t.stamp) and self._cells(t) is not None

    def waiting_for(self) -> tuple[list[str], list[str]]:
        """(what the pending tick still lacks, what the agent has instead), as sentences."""
        t = self.clock.open_tick()
        if t is None:
            return [], []
        need, have = self.maps.explain_missing(t.map_stamp)
        for more_need, more_have in self._round_gaps(t):
            need += more_need
            have += more_have
        return need, have

    def _round_gaps(self, t: Tick):
        yield self.rounds.explain(t.stamp, self.ids)
        geometry = self.maps.geometry(t.map_stamp)
        if geometry is not None:
            yield self.rounds.explain_off_grid(t.stamp, geometry, self.tolerance_m(geometry), self.ids)

    def orphan_round(self) -> int | None:
        """The stamp of a complete round of poses and readings newer than the last answered step
        for which no status came, if any (a driver that forgot the status, or stamped it apart)."""
        pending = self.clock.pending
        return self.rounds.orphan(self.clock.stamp, None if pending is None else pending.stamp)

    def observe(self) -> tuple[torch.Tensor, torch.Tensor, Tick]:
        """Apply the pending tick to the memory; returns (obs [C,H,W], mask [A], tick).

        Call only when :meth:`ready` is True.
        """
        t = self.clock.pending
        assert t is not None and self.ready()
        cells = self._cells(t)
        positions = torch.tensor([cells], dtype=torch.long)  # [1,N,2]
        readings = torch.tensor([[0.0 if v is None else v for v in self.rounds.readings(t.stamp)]],
                                dtype=torch.float32)  # [1,N]
        walls = self.maps.entry(t.map_stamp)[0].unsqueeze(0)
        here = self.rounds.present(t.stamp)
        self.rounds.remember_cells(cells, here)
        fresh, note = self.clock.advance(t)
        if note:
            self.notes.append(note)
        if len(here) < self.num_agents:  # a teammate taken out: record only the readings that came
            self.team.record(walls, positions[:, here], readings[:, here], fresh)
        else:
            self.team.record(walls, positions, readings, fresh)
        obs, mask = self.team.observe(self.observation, positions, walls, self.index)
        self.rounds.release(t.stamp)  # older stamps can never be answered again
        return obs, mask, t
