"""What the simulator watches besides the moves: other drivers on its topics.

A second graph on the same ROS_DOMAIN_ID and namespace publishes statuses with another
``EpisodeStatus.session``; a map on the map topic that the simulator did not publish replaces the
latched map that late-joining agents get. The simulator reports both on ``/diagnostics`` (and in
the log) and re-publishes its own map ``REPUBLISH_DELAY_S`` later (at most once per
``REPUBLISH_S``), so the team's map is the latched one again; the delay lets the agents see the
foreign map and report it before it is superseded (the map topic keeps one message).
"""

from __future__ import annotations

import time
from collections import deque

from diagnostic_msgs.msg import DiagnosticStatus
from medc_common import contract
from medc_interfaces.msg import EpisodeStatus
from nav_msgs.msg import OccupancyGrid

#: Seconds between two re-publications of the simulator's own map.
REPUBLISH_S = 2.0
#: Seconds from a foreign map to the re-publication of the simulator's own.
REPUBLISH_DELAY_S = 0.5
#: Seconds after the last foreign status or map before the report goes back to OK.
CLEAR_S = 10.0


def _key(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class GraphWatch:
    """Subscriptions of a SimNode to its own status and map topics (see the module docstring)."""

    def __init__(self, sim) -> None:
        self.sim = sim
        ns = sim.names_ns
        self.foreign_sessions: dict[str, float] = {}
        self.foreign_maps = 0
        self._own_maps: deque[int] = deque(maxlen=16)
        self._republished = 0.0
        self._republish_at: float | None = None
        self._last_foreign = 0.0
        sim.create_subscription(EpisodeStatus, contract.status_topic(ns), self.on_status,
                                contract.RELIABLE_QOS)
        sim.create_subscription(OccupancyGrid, contract.map_topic(ns), self.on_map, contract.MAP_READER_QOS)
        sim.create_timer(1.0, self._clear)
        sim.create_timer(0.1, self._republish)

    def own_map(self, stamp) -> None:
        """The simulator published a map with ``info.map_load_time`` ``stamp``."""
        self._own_maps.append(_key(stamp))

    def on_status(self, msg: EpisodeStatus) -> None:
        session = str(msg.session)
        if session == self.sim.session:
            return
        now = time.monotonic()
        self.foreign_sessions[session] = now
        self._last_foreign = now
        sessions = ", ".join(sorted(s or "(none)" for s in self.foreign_sessions))
        self.sim.health.set("graph", DiagnosticStatus.WARN, (
            f"another driver publishes on {contract.status_topic(self.sim.namespace_)} (sessions "
            f"{sessions}; this simulator is {self.sim.session}): a second graph shares this ROS_DOMAIN_ID "
            "and namespace; give each graph its own ROS_DOMAIN_ID or namespace"))

    def on_map(self, msg: OccupancyGrid) -> None:
        if not self.sim.started or _key(msg.info.map_load_time) in self._own_maps:
            return
        now = time.monotonic()
        self.foreign_maps += 1
        self._last_foreign = now
        self.sim.health.set("map", DiagnosticStatus.WARN, (
            f"a map this simulator did not publish came on {contract.map_topic(self.sim.namespace_)} "
            f"(map_load_time {msg.info.map_load_time.sec}.{msg.info.map_load_time.nanosec:09d}, origin "
            f"({msg.info.origin.position.x:g}, {msg.info.origin.position.y:g})); re-publishing the "
            "episode's map"))
        if self._republish_at is None:
            self._republish_at = max(now + REPUBLISH_DELAY_S, self._republished + REPUBLISH_S)

    def _republish(self) -> None:
        if self._republish_at is None or time.monotonic() < self._republish_at:
            return
        self._republish_at = None
        self._republished = time.monotonic()
        if not self.sim.finished:
            self.sim.map_pub.publish(self.sim.map_msg())

    def _clear(self) -> None:
        if self._last_foreign and time.monotonic() - self._last_foreign > CLEAR_S:
            self._last_foreign = 0.0
            self.foreign_sessions.clear()
            for part in ("graph", "map"):
                if self.sim.health.level(part) != DiagnosticStatus.OK:
                    self.sim.health.set(part, DiagnosticStatus.OK, "no other driver heard for "
                                        f"{CLEAR_S:g} s")
