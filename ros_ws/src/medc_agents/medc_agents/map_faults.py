"""An agent's map faults: a map refused, or a map from elsewhere (none of the team's latest poses
lie on it), reported on /diagnostics (condition ``map``) until a step goes on past it.

Owned by :class:`medc_agents.node.AgentNode`: it hands each map taken or refused and each step
decided to a :class:`MapFaults`, and its watch timer calls :meth:`MapFaults.check_due`.
"""

from __future__ import annotations

import time
from collections import Counter

from diagnostic_msgs.msg import DiagnosticStatus

from medc_agents.team_episode import Tick
from medc_agents.team_messages import show_stamp, stamp_key

#: Seconds after a map no status names before it is checked against the team's poses.
MAP_CHECK_S = 1.0


class MapFaults:
    """The ``map`` condition of one agent node: the fault reported and the maps waiting for their
    check against the team's poses.

    A fault is over once a step is decided on the map reported, on a map received after it, or on
    the map named by an episode status that came after the fault (the driver goes on with its own
    map, even one it sent before).
    """

    def __init__(self, observer, health, logger, dropped_by: Counter | None = None) -> None:
        """``observer``: the agent's TeamObserver; ``health``: its Health; ``logger``: its node's;
        ``dropped_by``: its count of dropped messages by kind (a refused map adds 'map')."""
        self.observer = observer
        self.health = health
        self.logger = logger
        self.dropped_by = Counter() if dropped_by is None else dropped_by
        #: The fault reported: (the count of maps offered when it came, the step then waiting for
        #: its inputs), until it is over; None without one.
        self.fault: tuple[int, Tick | None] | None = None
        #: map_load_time key -> when the map came, until it is checked.
        self.checks: dict[int, float] = {}

    def take(self, msg) -> bool:
        """Hand the walls map ``msg`` to the observer; False when it is refused (counted, and a
        fault on /diagnostics once per map and reason)."""
        key = stamp_key(msg.info.map_load_time)
        try:
            self.observer.add_map(msg)
        except ValueError as exc:
            self.dropped_by["map"] += 1
            self.refused(key, exc)
            return False
        self.taken(key)
        return True

    def refused(self, key: int, exc: Exception) -> None:
        """The map with ``info.map_load_time`` ``key`` was refused for ``exc``."""
        self._report(self.observer.maps.offered, f"map with map_load_time {show_stamp(key)} refused: {exc}; "
                     "a step that names it waits for a map it can take")

    def taken(self, key: int) -> None:
        """The map ``key`` was taken: a map no status names yet is checked against the team's poses a
        moment later (a new area's first poses come just after its map)."""
        self.checks[key] = time.monotonic()

    def check_due(self) -> None:
        """Check every map taken MAP_CHECK_S ago or more (a failing check is logged, never raised)."""
        now = time.monotonic()
        for key in [k for k, at in self.checks.items() if now - at >= MAP_CHECK_S]:
            del self.checks[key]
            try:
                self.check(key)
            except Exception as exc:  # a report must never take the node down
                self.logger.error(f"map check failed: {type(exc).__name__}")

    def check(self, key: int) -> None:
        """Report a map none of the team's latest poses lie on (a map from elsewhere) that no status
        names: it is kept aside and used only when an episode status names it."""
        o = self.observer
        geometry = o.maps.geometry(key)
        xys = o.rounds.latest_xy()
        if geometry is None or not xys or key in o.clock.maps_in_use():
            return
        on = 0
        for xy in xys:
            try:
                geometry.xy_to_cell(*xy, o.tolerance_m(geometry))
                on += 1
            except ValueError:
                pass
        if on == 0:
            self._report(o.maps.arrival(key), (
                f"map with map_load_time {show_stamp(key)} (origin ({geometry.origin_x:g}, "
                f"{geometry.origin_y:g}) m) holds none of the team's {len(xys)} latest poses: held; the "
                "team keeps the map its episode status names and uses this one only when a status names it"))

    def decided(self, tick: Tick) -> None:
        """A step was decided on the map ``tick`` names: that map needs no check, and a fault it
        goes on past is over."""
        self.checks.pop(tick.map_stamp, None)  # a map a status names is the driver's
        if self.fault is None:
            return
        offered, waiting = self.fault
        arrival = self.observer.maps.arrival(tick.map_stamp)
        if tick != waiting or (arrival is not None and arrival >= offered):
            self.fault = None
            self.health.set("map", DiagnosticStatus.OK, f"deciding on the map with map_load_time "
                            f"{show_stamp(tick.map_stamp)}, which the episode status names")

    def _report(self, offered: int, message: str) -> None:
        self.fault = (offered, self.observer.clock.open_tick())
        self.health.set("map", DiagnosticStatus.WARN, message)
