"""What an agent holds of its team's messages until a step is answered (no ROS here): the walls
maps by ``info.map_load_time`` (:class:`MapStore`) and the poses and readings by header stamp
(:class:`TeamRounds`), each able to say what a step still lacks, for the node's stall report.
Messages reach them checked (:mod:`medc_agents.team_messages`); times are stamp keys (integer ns).
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from medc_common.contract import GridGeometry

from medc_agents.team_messages import show_stamp

#: How many distinct stamps of poses/readings to keep while waiting for a status.
STAMP_HISTORY = 16
#: How many maps to hold; the oldest go first, but never one the team's episode or pending step names.
KEEP_MAPS = 4

Sentences = tuple[list[str], list[str]]


class MapStore:
    """The walls maps received: the latest :data:`KEEP_MAPS`, but never letting go of one the
    episode in play or the pending step uses, so a burst of other maps cannot take the team's map
    away."""

    def __init__(self) -> None:
        #: map_load_time key -> (walls bool [H,W], geometry, header stamp key)
        self._maps: OrderedDict[int, tuple[torch.Tensor, GridGeometry, int]] = OrderedDict()
        #: The geometry of the latest map taken.
        self.latest: GridGeometry | None = None
        #: Why the last map was dropped (for the stall report), if one was.
        self.last_drop = ""
        #: Why each of the latest maps refused was refused, by ``info.map_load_time``.
        self.refused: OrderedDict[int, str] = OrderedDict()
        #: Maps offered so far (taken or refused); the count when each held map came.
        self.offered = 0
        self._arrival: dict[int, int] = {}

    def __contains__(self, load: int) -> bool:
        return load in self._maps

    def __len__(self) -> int:
        return len(self._maps)

    def put(self, load: int, walls: torch.Tensor, geometry: GridGeometry, header: int, keep) -> None:
        """Hold the map with ``info.map_load_time`` ``load``; beyond :data:`KEEP_MAPS` maps the
        oldest whose stamp is not in ``keep`` are let go."""
        self._maps[load] = (walls, geometry, header)
        self._maps.move_to_end(load)
        self.latest = geometry
        self.offered += 1
        self._arrival[load] = self.offered
        self.refused.pop(load, None)
        keep = set(keep)
        for old in [k for k in self._maps if k not in keep][:max(0, len(self._maps) - KEEP_MAPS)]:
            del self._maps[old]
            del self._arrival[old]

    def refuse(self, load: int, reason: str) -> None:
        """The map with ``info.map_load_time`` ``load`` was refused for ``reason`` (kept for the stall
        report of a step that names it)."""
        self.offered += 1
        self.last_drop = f"map with map_load_time {show_stamp(load)}: {reason}"
        self.refused[load] = reason
        self.refused.move_to_end(load)
        while len(self.refused) > STAMP_HISTORY:
            self.refused.popitem(last=False)

    def arrival(self, load: int) -> int | None:
        """When the held map ``load`` came, as the count of maps offered by then (None: not held)."""
        return self._arrival.get(load)

    def entry(self, load: int) -> tuple[torch.Tensor, GridGeometry, int] | None:
        """(walls, geometry, header stamp) of the map with ``info.map_load_time`` ``load``, if held."""
        return self._maps.get(load)

    def geometry(self, load: int) -> GridGeometry | None:
        """The grid geometry of the map with ``info.map_load_time`` ``load``, if held."""
        entry = self._maps.get(load)
        return None if entry is None else entry[1]

    def explain_missing(self, load: int) -> Sentences:
        """(what is needed, what is here instead) when a step names map ``load``; empty when held."""
        if load in self._maps:
            return [], []
        need = [f"the map with info.map_load_time {show_stamp(load)} (the status's map_stamp)"]
        if load in self.refused:
            return need, [f"that map was refused: {self.refused[load]}"]
        have = []
        if self._maps:
            have.append("maps with info.map_load_time " + ", ".join(show_stamp(k) for k in self._maps))
            for held, (_, _, header) in self._maps.items():
                if header == load and held != load:
                    have.append(f"the map whose header.stamp is {show_stamp(header)} has "
                                f"info.map_load_time {show_stamp(held)}: map_stamp must equal "
                                "info.map_load_time")
        elif self.last_drop:
            have.append(f"no usable map: the last one was dropped ({self.last_drop})")
        else:
            have.append("no map on the map topic")
        return need, have


class TeamRounds:
    """The team's poses (raw map-frame x, y) and readings by header stamp, the last
    :data:`STAMP_HISTORY` stamps; what was last heard of each agent; which teammates are taken out
    of the team (docs/ros-reference.md, "A lost UAV": steps are decided without their pose and reading, and
    their last cell stays in the observation)."""

    KINDS = ("pose", "reading")

    def __init__(self, num_agents: int) -> None:
        self.num_agents = num_agents
        self._stores: dict[str, OrderedDict[int, list]] = {kind: OrderedDict() for kind in self.KINDS}
        #: For the stall report: latest stamp received and latest drop reason, per (kind, agent).
        self.latest: dict[tuple[str, int], int] = {}
        self.last_drop: dict[tuple[str, int], str] = {}
        #: Teammates taken out of the team.
        self.absent: set[int] = set()
        self._last_xy: list[tuple[float, float] | None] = [None] * num_agents
        self._last_cells: list[tuple[int, int] | None] = [None] * num_agents
        #: Poses held before the map of their step was known, not yet checked against it: (stamp, agent).
        self.unverified: set[tuple[int, int]] = set()

    def _of(self, kind: str, key: int) -> list:
        return self._stores[kind].get(key) or [None] * self.num_agents

    def add(self, kind: str, idx: int, key: int, value, verified: bool = True) -> None:
        """Hold agent ``idx``'s ``kind`` ('pose': (x, y); 'reading': a value) stamped ``key``;
        ``verified`` False: a pose not yet checked against the map of its step (:meth:`verify`)."""
        store = self._stores[kind]
        if key not in store:
            store[key] = [None] * self.num_agents
            while len(store) > STAMP_HISTORY:
                old, _ = store.popitem(last=False)
                self.unverified = {u for u in self.unverified if u[0] != old}
        store[key][idx] = value
        if kind == "pose":
            (self.unverified.discard if verified else self.unverified.add)((key, idx))
        self.latest[(kind, idx)] = key
        if kind == "pose":
            self._last_xy[idx] = value

    def has_verified_pose(self, idx: int, key: int) -> bool:
        """Whether a pose of agent ``idx`` stamped ``key`` is held and lies on the map it was checked on."""
        xys = self._stores["pose"].get(key)
        return xys is not None and xys[idx] is not None and (key, idx) not in self.unverified

    def verify(self, key: int, geometry: GridGeometry, tolerance_m: float) -> list[tuple[int, str]]:
        """Check the unverified poses stamped ``key`` against ``geometry`` (the map of their step):
        those on it are kept, the others dropped. Returns (agent, reason) of each pose dropped."""
        dropped = []
        xys = self._stores["pose"].get(key)
        for k, idx in sorted(u for u in self.unverified if u[0] == key):
            self.unverified.discard((k, idx))
            if xys is None or xys[idx] is None:
                continue
            try:
                geometry.xy_to_cell(*xys[idx], tolerance_m)
            except ValueError as exc:
                xys[idx] = None
                self.drop("pose", idx, str(exc))
                dropped.append((idx, str(exc)))
        return dropped

    def drop(self, kind: str, idx: int, reason: str) -> None:
        """Remember why agent ``idx``'s last ``kind`` was dropped."""
        self.last_drop[(kind, idx)] = reason

    def latest_xy(self) -> list[tuple[float, float]]:
        """Each agent's latest pose received (raw map-frame x, y), for those heard from."""
        return [xy for xy in self._last_xy if xy is not None]

    def readings(self, key: int) -> list[float | None]:
        """Each agent's reading stamped ``key`` (None: not here)."""
        return list(self._of("reading", key))

    def present(self, key: int) -> list[int]:
        """The agents whose pose and reading stamped ``key`` are both here."""
        xys, rd = self._of("pose", key), self._of("reading", key)
        return [j for j in range(self.num_agents) if xys[j] is not None and rd[j] is not None]

    def missing(self, key: int) -> dict[int, list[str]]:
        """Agent index -> kinds ('pose', 'reading') stamped ``key`` still missing."""
        out: dict[int, list[str]] = {}
        for kind in self.KINDS:
            for j, value in enumerate(self._of(kind, key)):
                if value is None:
                    out.setdefault(j, []).append(kind)
        return out

    def readings_complete(self, key: int) -> bool:
        """Every agent not taken out has a reading stamped ``key``."""
        rd = self._stores["reading"].get(key)
        return rd is not None and all(v is not None or j in self.absent for j, v in enumerate(rd))

    def cells(self, key: int, geometry: GridGeometry, tolerance_m: float, own: int) -> list | None:
        """Every agent's cell at ``key`` on ``geometry``'s grid; an absent teammate without a pose
        keeps its last cell (agent ``own``'s when it has none). None when ``own``'s pose or a
        present teammate's is missing, or one lies off the grid."""
        xys = self._stores["pose"].get(key)
        if xys is None or xys[own] is None:
            return None
        cells = []
        try:
            for j, xy in enumerate(xys):
                if xy is None and j not in self.absent:
                    return None
                cells.append(None if xy is None else geometry.xy_to_cell(*xy, tolerance_m))
        except ValueError:
            return None
        mine = cells[own]
        return [c if c is not None else (self._last_cells[j] or mine) for j, c in enumerate(cells)]

    def remember_cells(self, cells: list, here: list[int]) -> None:
        """Keep the cells of the agents ``here`` as their last known ones."""
        for j in here:
            self._last_cells[j] = cells[j]

    def orphan(self, answered: int, pending: int | None) -> int | None:
        """The stamp of a complete round newer than the ``answered`` stamp (-1: none yet) that is
        not the ``pending`` step's, if any (a driver that forgot the status, or stamped it apart)."""
        poses, readings = self._stores["pose"], self._stores["reading"]
        for key in reversed(poses):
            if key <= answered and answered >= 0:
                continue
            rd = readings.get(key)
            if None not in poses[key] and rd is not None and None not in rd and pending != key:
                return key
        return None

    def explain(self, key: int, ids: list[str]) -> Sentences:
        """(what is needed, what is here instead) of the poses and readings stamped ``key``."""
        need, have = [], []
        for kind in self.KINDS:
            for j, value in enumerate(self._of(kind, key)):
                if value is not None or j in self.absent:
                    continue
                need.append(f"the {kind} of {ids[j]} stamped {show_stamp(key)}")
                latest = self.latest.get((kind, j))
                if latest is None:
                    have.append(f"no {kind} of {ids[j]} yet")
                else:
                    have.append(f"latest {kind} of {ids[j]} stamped {show_stamp(latest)} "
                                f"({(latest - key) / 1000.0:+.3f} us from the status)")
                if (kind, j) in self.last_drop:
                    have.append(f"last {kind} of {ids[j]} dropped: {self.last_drop[(kind, j)]}")
        return need, have

    def explain_off_grid(self, key: int, geometry: GridGeometry, tolerance_m: float,
                         ids: list[str]) -> Sentences:
        """(what is needed, why) for each pose stamped ``key`` that lies off ``geometry``'s grid."""
        need, have = [], []
        for j, xy in enumerate(self._stores["pose"].get(key) or []):
            if xy is None:
                continue
            try:
                geometry.xy_to_cell(*xy, tolerance_m)
            except ValueError as exc:
                need.append(f"a pose of {ids[j]} on the map")
                have.append(f"{ids[j]}: {exc}")
        return need, have

    def release(self, key: int) -> None:
        """Let go of every round stamped ``key`` or earlier: they can never be answered again."""
        for store in self._stores.values():
            for old in [k for k in store if k <= key]:
                del store[old]
        self.unverified = {u for u in self.unverified if u[0] > key}
