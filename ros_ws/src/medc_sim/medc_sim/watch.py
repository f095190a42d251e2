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
from collections.abc import Callable

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
    """Subscriptions of a simulator to its own status and map topics (see the module docstring)."""

    def __init__(self, node, names_ns: str | None, namespace: str, session: str, health, *,
                 started: Callable[[], bool], finished: Callable[[], bool],
                 republish: Callable[[], None], clock: Callable[[], float] = time.monotonic) -> None:
        """``node``: the simulator node its subscriptions and timers are made on, under ``names_ns``
        (contract.team_namespace); ``namespace``: the team's, fully qualified, for the reports;
        ``session``: the simulator's own; ``health``: its Health; ``started``, ``finished``: whether
        the simulator has started and finished; ``republish``: publishes the episode's map again."""
        self.namespace = namespace
        self.session = session
        self.health = health
        self.started = started
        self.finished = finished
        self.republish = republish
        self.clock = clock
        ns = names_ns
        self.foreign_sessions: dict[str, float] = {}
        self.foreign_maps = 0
        self._own_maps: deque[int] = deque(maxlen=16)
        self._republished = 0.0
        self._republish_at: float | None = None
        self._last_foreign = 0.0
        node.create_subscription(EpisodeStatus, contract.status_topic(ns), self.on_status,
                                 contract.RELIABLE_QOS)
        node.create_subscription(OccupancyGrid, contract.map_topic(ns), self.on_map, contract.MAP_READER_QOS)
        node.create_timer(1.0, self._clear)
        node.create_timer(0.1, self._republish)

    def own_map(self, stamp) -> None:
        """The simulator published a map with ``info.map_load_time`` ``stamp``."""
        self._own_maps.append(_key(stamp))

    def on_status(self, msg: EpisodeStatus) -> None:
        session = str(msg.session)
        if session == self.session:
            return
        now = self.clock()
        self.foreign_sessions[session] = now
        self._last_foreign = now
        sessions = ", ".join(sorted(s or "(none)" for s in self.foreign_sessions))
        self.health.set("graph", DiagnosticStatus.WARN, (
            f"another driver publishes on {contract.status_topic(self.namespace)} (sessions "
            f"{sessions}; this simulator is {self.session}): a second graph shares this ROS_DOMAIN_ID "
            "and namespace; give each graph its own ROS_DOMAIN_ID or namespace"))

    def on_map(self, msg: OccupancyGrid) -> None:
        if not self.started() or _key(msg.info.map_load_time) in self._own_maps:
            return
        now = self.clock()
        self.foreign_maps += 1
        self._last_foreign = now
        self.health.set("map", DiagnosticStatus.WARN, (
            f"a map this simulator did not publish came on {contract.map_topic(self.namespace)} "
            f"(map_load_time {msg.info.map_load_time.sec}.{msg.info.map_load_time.nanosec:09d}, origin "
            f"({msg.info.origin.position.x:g}, {msg.info.origin.position.y:g})); re-publishing the "
            "episode's map"))
        if self._republish_at is None:
            self._republish_at = max(now + REPUBLISH_DELAY_S, self._republished + REPUBLISH_S)

    def _republish(self) -> None:
        if self._republish_at is None or self.clock() < self._republish_at:
            return
        self._republish_at = None
        self._republished = self.clock()
        if not self.finished():
            self.republish()

    def _clear(self) -> None:
        if self._last_foreign and self.clock() - self._last_foreign > CLEAR_S:
            self._last_foreign = 0.0
            self.foreign_sessions.clear()
            for part in ("graph", "map"):
                if self.health.level(part) != DiagnosticStatus.OK:
                    self.health.set(part, DiagnosticStatus.OK, "no other driver heard for "
                                        f"{CLEAR_S:g} s")
