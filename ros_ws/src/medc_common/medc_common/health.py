"""A node's health on ``/diagnostics``: a ~1 Hz heartbeat, states that last, one-off events.

Monitors (diagnostic aggregators, rqt_robot_monitor, Foxglove's diagnostics panel) expect every
node to publish its status about once a second and show a node as stale when it stops. A
:class:`Health` keeps the latest status of each named condition of one node (its ``team step``,
its ``team``, its ``inputs`` ...) and publishes all of them, with a summary status named after the
node, every ``period_s`` (docs/ros-reference.md, "Diagnostics"). A change is published at once too, and
logged at the level it is published with (WARN on /diagnostics = a warning in the log; ERROR =
an error; OK = info), so the log and /diagnostics always agree.

:func:`run_id` makes the per-run ids of moves (``AgentMove.sender``) and of a driver's statuses
(``EpisodeStatus.session``).
"""

from __future__ import annotations

import contextlib
import secrets
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from medc_common.contract import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
#: Heartbeat period (seconds): what monitors expect (about 1 Hz).
HEARTBEAT_S = 1.0
_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


def run_id() -> str:
    """A random per-run id (16 hex digits): a node's ``sender`` or a driver's ``session``."""
    return secrets.token_hex(8)


def level_name(level: bytes) -> str:
    """'OK', 'WARN' or 'ERROR' of a DiagnosticStatus level."""
    return _NAMES.get(level, "STALE")


class Health:
    """The diagnostics of one node (see the module docstring).

    ``hardware_id``: what every status names as its hardware (an agent's id, ``driver``).
    ``summary``: a callable returning ``{key: value}`` strings added to the heartbeat's status.
    """

    def __init__(self, node, hardware_id: str, summary=None, period_s: float = HEARTBEAT_S) -> None:
        self.node = node
        self.hardware_id = hardware_id
        self.summary = summary
        self.pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        self.states: dict[str, DiagnosticStatus] = {}
        self.started = time.monotonic()
        self.beats = 0
        self.timer = node.create_timer(period_s, self.beat) if period_s > 0 else None
        #: The node's medc_common.auth_node.NodeAuth once it has one: every array is signed with it.
        self.auth = None

    def _status(self, part: str, level: bytes, message: str, values: dict | None) -> DiagnosticStatus:
        status = DiagnosticStatus(level=level, name=f"{self.node.get_name()}: {part}", message=message,
                                  hardware_id=self.hardware_id)
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()]
        return status

    def _log(self, level: bytes, message: str) -> None:
        # rclpy wants one severity per call site: one call per level.
        log = self.node.get_logger()
        if level == ERROR:
            log.error(message)
        elif level == WARN:
            log.warning(message)
        else:
            log.info(message)

    def _publish(self, statuses: list[DiagnosticStatus]) -> None:
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self.node.get_clock().now().to_msg()
        if self.auth is not None:
            self.auth.sign_diagnostics(array, DIAGNOSTICS_TOPIC)
        # The context may be shutting down: a heartbeat is not worth a traceback.
        with contextlib.suppress(Exception):
            self.pub.publish(array)

    def set(self, part: str, level: bytes, message: str, values: dict | None = None,
            log: bool = True) -> bool:
        """Set condition ``part`` (e.g. ``team step``) to ``level``/``message``; published (and
        logged, unless ``log`` is False) at once when it changed. Returns whether it changed."""
        old = self.states.get(part)
        if old is not None and (old.level, old.message) == (level, message):
            return False
        status = self._status(part, level, message, values)
        self.states[part] = status
        if log:
            self._log(level, message)
        self._publish([status])
        return True

    def level(self, part: str) -> bytes:
        """The current level of ``part`` (OK when never set)."""
        status = self.states.get(part)
        return OK if status is None else status.level

    def event(self, part: str, level: bytes, message: str, values: dict | None = None) -> None:
        """Log and publish one event (e.g. a driver restart) without keeping it as a state."""
        self._log(level, message)
        self._publish([self._status(part, level, message, values)])

    def beat(self) -> None:
        """Publish the heartbeat: the node's summary status and every condition's latest status."""
        self.beats += 1
        worst = max((s.level for s in self.states.values()), default=OK)
        bad = [s.message for s in self.states.values() if s.level != OK]
        values = {"uptime_s": f"{time.monotonic() - self.started:.0f}"}
        if self.summary is not None:
            values.update(self.summary())
        message = "; ".join(bad)[:500] if bad else "running"
        status = DiagnosticStatus(level=worst, name=self.node.get_name(), message=message,
                                  hardware_id=self.hardware_id)
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
        self._publish([status, *self.states.values()])
