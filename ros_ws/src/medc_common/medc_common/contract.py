"""The topic contract between the simulator (or a real UAV driver) and the agent nodes.

Everything a node needs to agree on lives here: topic and service names, QoS profiles, frames,
agent ids, and the grid <-> map-frame conversion. docs/ros-reference.md describes the same
contract for people.

Names are relative to the team's namespace, which is each node's ROS namespace (DEFAULT_NAMESPACE
unless remapped: ``--ros-args -r __ns:=/team2`` moves a whole team); only names that are global by
ROS convention (``/diagnostics``) are absolute.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

MAP_FRAME = "map"
#: The namespace the team's nodes are created in when nothing remaps it.
DEFAULT_NAMESPACE = "/medc"

#: Sensor data (poses, readings): best effort, keep last 5, as a real driver publishes them.
SENSOR_QOS: QoSProfile = qos_profile_sensor_data
#: Moves and episode status: every one matters.
RELIABLE_QOS = QoSProfile(
    depth=20,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.VOLATILE,
)
#: Walls map and policy selection: latched, so a node that starts late still gets the last one.
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Readers of the map topic: latched like the publisher, but a queue of 8, so that a map arriving
#: just before another (a foreign one, then the driver's next) is still seen and checked.
MAP_READER_QOS = QoSProfile(
    depth=8,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Episode results: every one kept (up to 1000) for readers that join late or fall behind.
RESULTS_QOS = QoSProfile(
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: What an agent id looks like: agent_<i>, i = the agent's index in the environment.
AGENT_ID_PATTERN = re.compile(r"^agent_(\d+)$")


def agent_id(index: int) -> str:
    """The id of the agent at env index ``index``: ``agent_<index>``."""
    return f"agent_{index}"


def agent_node_name(index: int) -> str:
    """The default ROS node name of the agent at env index ``index``: ``medc_agent_<index>``."""
    return f"medc_{agent_id(index)}"


def agent_ids(num_agents: int) -> list[str]:
    """The ids of a team of ``num_agents``: ``agent_0`` .. ``agent_{n-1}`` (env agent order)."""
    if num_agents < 1:
        raise ValueError(f"num_agents must be >= 1, got {num_agents}")
    return [agent_id(i) for i in range(num_agents)]


def agent_index(agent_id: str, num_agents: int) -> int:
    """The env index of ``agent_id`` in a team of ``num_agents``.

    Raises:
        ValueError: not of the form ``agent_<i>`` with ``0 <= i < num_agents``.
    """
    m = AGENT_ID_PATTERN.match(agent_id)
    if not m or int(m.group(1)) >= num_agents:
        raise ValueError(f"unknown agent id {agent_id!r}: expected agent_0 .. agent_{num_agents - 1}")
    return int(m.group(1))


def _ns(namespace: str) -> str:
    ns = "/" + namespace.strip("/")
    return "" if ns == "/" else ns


def _name(namespace: str | None, relative: str) -> str:
    """``relative`` as nodes use it (``namespace`` None: resolved by ROS against the node's own
    namespace, so ``-r __ns:=/team2`` moves it), or its fully-qualified name under ``namespace``."""
    return relative if namespace is None else f"{_ns(namespace)}/{relative}"


# Every name of the contract is relative: a node passes ``None`` (RELATIVE) as the namespace and
# ROS resolves the name against the node's namespace (DEFAULT_NAMESPACE unless remapped); a tool
# outside the team (a monitor, a test, a recorder) passes the team's namespace and gets the
# fully-qualified name, e.g. pose_topic("/medc", "agent_0") == "/medc/agent_0/pose".

#: The namespace argument that gives a relative name (what the team's nodes create).
RELATIVE = None
#: The description of the ``namespace`` parameter of the simulator, the agents and the bridge.
NAMESPACE_HELP = ("Empty: the team's names are relative to the node's namespace (/medc unless "
                  "-r __ns:=/team2 moves them). A namespace pins them under it instead (an older "
                  "launch file's way); it must not contradict a remapped node namespace")


def pose_topic(namespace: str | None, agent_id: str) -> str:
    """geometry_msgs/PoseStamped, SENSOR_QOS: the agent's position in the map frame."""
    return _name(namespace, f"{agent_id}/pose")


def radiation_topic(namespace: str | None, agent_id: str) -> str:
    """medc_interfaces/RadiationReading, SENSOR_QOS: the agent's latest measurement."""
    return _name(namespace, f"{agent_id}/radiation")


def move_topic(namespace: str | None, agent_id: str) -> str:
    """medc_interfaces/AgentMove, RELIABLE_QOS: the move the agent's policy chose."""
    return _name(namespace, f"{agent_id}/move")


def policy_topic(namespace: str | None, agent_id: str) -> str:
    """std_msgs/String, LATCHED_QOS: a bundle path (or ``ipfs://``/CID via the bridge) to run."""
    return _name(namespace, f"{agent_id}/policy")


def team_policy_topic(namespace: str | None) -> str:
    """std_msgs/String, LATCHED_QOS: a bundle path every agent of the team switches to."""
    return _name(namespace, "team/policy")


def map_topic(namespace: str | None) -> str:
    """nav_msgs/OccupancyGrid, LATCHED_QOS: the walls of the current episode (>= 50 = wall)."""
    return _name(namespace, "map")


def status_topic(namespace: str | None) -> str:
    """medc_interfaces/EpisodeStatus, RELIABLE_QOS: one per team step, after poses and readings."""
    return _name(namespace, "episode")


def results_topic(namespace: str | None) -> str:
    """medc_interfaces/EpisodeStatus, RESULTS_QOS: the closing status (done) of every episode."""
    return _name(namespace, "episode_result")


def estimate_topic(namespace: str | None) -> str:
    """geometry_msgs/PoseWithCovarianceStamped, ESTIMATE_QOS: the team's source estimate in the map
    frame (posterior mean, covariance of the position), once per team step."""
    return _name(namespace, "team/source_estimate")


def posterior_topic(namespace: str | None) -> str:
    """nav_msgs/OccupancyGrid, LATCHED_QOS: the team's source posterior as a heat map on the walls
    map's grid (100 = the most probable cell), at the publisher's ``estimate_map_rate_hz``."""
    return _name(namespace, "team/source_posterior")


def declaration_topic(namespace: str | None) -> str:
    """medc_interfaces/SourceDeclaration, RELIABLE_QOS: the team declares the source localised (once
    per episode); a driver ends the episode on it."""
    return _name(namespace, "team/source_declared")


def team_name(namespace: str | None, name: str) -> str:
    """A name a node was given (a parameter): absolute (``/...``) and private (``~...``) names as they
    are, a relative one under ``namespace`` (None: left relative, for ROS to resolve)."""
    return name if namespace is None or name.startswith(("/", "~")) else _name(namespace, name)


#: The registry bridge's services (medc_interfaces/srv): RequestExperts, FetchBundle, SubmitReview.
REGISTRY_SERVICES = ("request_experts", "fetch_bundle", "submit_review")


def registry_service(namespace: str | None, name: str) -> str:
    """The registry bridge's service ``name`` (one of REGISTRY_SERVICES): ``registry/<name>``."""
    if name not in REGISTRY_SERVICES:
        raise ValueError(f"unknown registry service {name!r}: expected one of {', '.join(REGISTRY_SERVICES)}")
    return _name(namespace, f"registry/{name}")


def check_namespace(namespace: str) -> str:
    """``namespace`` as a fully-qualified ROS namespace (a leading ``/`` added: ``team2`` ->
    ``/team2``; a trailing one removed).

    Raises:
        ValueError: not a valid ROS namespace (letters, digits and ``_`` in ``/``-separated tokens
        that do not start with a digit), with the reason.
    """
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    if not isinstance(namespace, str):
        raise ValueError(f"namespace must be a string, got {namespace!r}")
    text = namespace.strip()
    full = "/" + text.strip("/") if text.strip("/") else "/"
    try:
        validate_namespace(full)
    except InvalidNamespaceException as exc:
        why = str(exc).splitlines()[0].removeprefix("Invalid namespace: ").rstrip(":")
        raise ValueError(f"namespace {namespace!r} is not a valid ROS namespace: {why}") from None
    return full


def team_namespace(node_namespace: str, parameter: str = "") -> tuple[str, str | None]:
    """Where a node's team lives: ``(fully-qualified namespace, namespace to build names with)``.

    The team's namespace is the node's own (DEFAULT_NAMESPACE unless ``-r __ns:=/team2`` or a
    launch file moves it): names are relative (None). A non-empty ``namespace`` parameter (kept for
    older launch and parameter files) pins the names under itself instead, as absolute names do in
    ROS; it may not contradict a node namespace that was moved away from the default.

    Raises:
        ValueError: an invalid namespace parameter, or one that differs from a remapped node
        namespace (the message names both and what to drop).
    """
    if not parameter or not parameter.strip():
        return node_namespace, RELATIVE
    pinned = check_namespace(parameter)
    if pinned == node_namespace:
        return node_namespace, RELATIVE
    if node_namespace != DEFAULT_NAMESPACE:
        raise ValueError(
            f"the namespace parameter {parameter!r} contradicts the node's namespace {node_namespace} "
            f"(-r __ns:={node_namespace} or a launch file's namespace): give the team's namespace once, "
            "preferably as -r __ns:=..., and leave the namespace parameter empty")
    return pinned, pinned


#: The source estimate: reliable, keep last 5, volatile (a monitor wants the latest ones).
ESTIMATE_QOS = QoSProfile(
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.VOLATILE,
)


#: Topic of the agents' diagnostics (diagnostic_msgs/DiagnosticArray): the ROS convention's
#: absolute ``/diagnostics``, so diagnostic aggregators and rqt_robot_monitor see it.
DIAGNOSTICS_TOPIC = "/diagnostics"
#: diagnostics: reliable, keep last 50, volatile (published when an agent's state changes).
DIAGNOSTICS_QOS = QoSProfile(
    depth=50,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.VOLATILE,
)

#: A cell is a wall when its OccupancyGrid value is >= this (0..49 and -1 unknown are free).
OCCUPIED_THRESHOLD = 50
#: The value the simulator publishes for a wall (and 0 for a free cell).
OCCUPIED = 100

# -- Frames (REP 103) ------------------------------------------------------------------------------
#
# The ``map`` frame is ENU: x east, y north, z up. The walls map (nav_msgs/OccupancyGrid) defines
# the grid in it as nav_msgs does: cell (i, j) -- column i, row j of the message -- is the square
# [i*r, (i+1)*r) x [j*r, (j+1)*r) of the grid frame whose pose in ``map`` is ``info.origin``
# (r = ``info.resolution``); ``data[j * width + i]`` is that cell, so row j = 0 of the message is
# the one at the origin, i.e. the southern row for an identity origin orientation.
#
# The training environment keeps cells as (row, col) with row 0 on top ("north", action N =
# row - 1). The one mapping between the two is
#
#     i = col,    j = height - 1 - row          (and back: col = i, row = height - 1 - j)
#
# so the environment's north (row - 1) is +y of the grid frame, east (col + 1) is +x.


def cell_to_ij(row: int, col: int, height: int) -> tuple[int, int]:
    """The OccupancyGrid cell (i = column, j = row of the message) of environment cell (row, col)."""
    return col, height - 1 - row


def ij_to_cell(i: int, j: int, height: int) -> tuple[int, int]:
    """The environment cell (row, col) of OccupancyGrid cell (i, j)."""
    return height - 1 - j, i


#: The 8 moves (actions 0..7 = N, NE, E, SE, S, SW, W, NW) as one-cell steps (di, dj) of the grid
#: frame: N = +y (j + 1), E = +x (i + 1). Equal to the environment's (drow, dcol) with drow = -dj.
MOVE_STEPS: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)
)
#: Heading of each move in the grid frame, radians counter-clockwise from +x (east), REP 103
#: yaw: N = pi/2, NE = pi/4, E = 0, ..., W = pi, NW = 3 pi/4. In the map frame add the origin's yaw.
MOVE_HEADINGS: tuple[float, ...] = tuple(math.atan2(dj, di) for di, dj in MOVE_STEPS)


@dataclass(frozen=True)
class GridGeometry:
    """Where the grid lies in the ``map`` frame: ``info.origin`` (x, y, yaw) and ``info.resolution``
    of the OccupancyGrid, and its size (``height`` rows = environment rows, ``width`` columns)."""

    height: int
    width: int
    resolution: float = 1.0
    origin_x: float = 0.0
    origin_y: float = 0.0
    origin_yaw: float = 0.0

    def cell_to_xy(self, row: int, col: int) -> tuple[float, float]:
        """Map-frame centre of environment cell (row, col): origin + R(yaw) (i + 0.5, j + 0.5) r."""
        i, j = cell_to_ij(row, col, self.height)
        gx, gy = (i + 0.5) * self.resolution, (j + 0.5) * self.resolution
        c, s = math.cos(self.origin_yaw), math.sin(self.origin_yaw)
        return self.origin_x + c * gx - s * gy, self.origin_y + s * gx + c * gy

    def xy_to_cell(self, x: float, y: float, tolerance: float = 0.0) -> tuple[int, int]:
        """The environment cell (row, col) whose square holds map-frame point (x, y) (z, yaw and
        the offset from the cell centre are ignored: a point anywhere in a cell snaps to it).
        ``tolerance`` (metres): a point at most this far outside the grid's edge (GNSS noise on the
        edge row) snaps to the nearest edge cell.

        Raises:
            ValueError: a coordinate is not finite or the point lies outside the grid (by more than
            ``tolerance``).
        """
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"position ({x}, {y}) is not finite")
        dx, dy = x - self.origin_x, y - self.origin_y
        c, s = math.cos(self.origin_yaw), math.sin(self.origin_yaw)
        gx, gy = c * dx + s * dy, -s * dx + c * dy
        i, j = math.floor(gx / self.resolution), math.floor(gy / self.resolution)
        if not (0 <= i < self.width and 0 <= j < self.height):
            # How far outside the grid's edge the point is (metres, in the grid frame).
            out_x = max(0.0, -gx, gx - self.width * self.resolution)
            out_y = max(0.0, -gy, gy - self.height * self.resolution)
            outside = math.hypot(out_x, out_y)
            if outside <= tolerance:
                return ij_to_cell(min(max(i, 0), self.width - 1), min(max(j, 0), self.height - 1),
                                  self.height)
            raise ValueError(
                f"position ({x:.3f}, {y:.3f}) m is outside the {self.height}x{self.width} grid of the map "
                f"(origin ({self.origin_x:g}, {self.origin_y:g}) m, yaw {self.origin_yaw:g} rad, "
                f"resolution {self.resolution:g} m) by {outside:.3f} m"
                + (f", more than the edge tolerance of {tolerance:g} m" if tolerance > 0 else "")
            )
        return ij_to_cell(i, j, self.height)

    def move_heading(self, action: int) -> float:
        """Map-frame yaw (REP 103, radians) of move ``action``."""
        return math.atan2(math.sin(MOVE_HEADINGS[action] + self.origin_yaw),
                          math.cos(MOVE_HEADINGS[action] + self.origin_yaw))


def yaw_of(q) -> float:
    """Yaw of a geometry_msgs/Quaternion that rotates about z only.

    Raises:
        ValueError: not finite, not a unit quaternion, or a rotation out of the x-y plane.
    """
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    if not all(math.isfinite(v) for v in (x, y, z, w)):
        raise ValueError("orientation is not finite")
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"orientation is not a unit quaternion (norm {norm:.4f})")
    if math.hypot(x, y) > 1e-3 * norm:
        raise ValueError("map origin is rotated out of the x-y plane; only a yaw is allowed")
    return 2.0 * math.atan2(z, w)


def geometry_of(msg) -> GridGeometry:
    """The GridGeometry a nav_msgs/OccupancyGrid defines.

    Raises:
        ValueError: resolution not positive/finite, origin not finite or rotated out of plane.
    """
    info = msg.info
    res = float(info.resolution)
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"map resolution {res} is not a positive number of metres")
    pos = info.origin.position
    if not (math.isfinite(pos.x) and math.isfinite(pos.y)):
        raise ValueError("map origin is not finite")
    return GridGeometry(int(info.height), int(info.width), res, float(pos.x), float(pos.y),
                        yaw_of(info.origin.orientation))


def walls_to_occupancy(walls) -> list[int]:
    """OccupancyGrid ``data`` of bool walls [H,W] (environment rows; numpy or a CPU tensor):
    100 = wall, 0 = free; message row j holds environment row H - 1 - j."""
    import numpy as np

    cells = np.asarray(walls, dtype=bool)[::-1]
    return (cells.astype(np.int8) * OCCUPIED).ravel().tolist()


def occupancy_to_walls(data, height: int, width: int):
    """bool numpy [H,W] walls (environment rows) of OccupancyGrid ``data``: value >= 50 is a wall."""
    import numpy as np

    cells = np.asarray(data, dtype=np.int16).reshape(height, width)
    return np.ascontiguousarray(cells[::-1] >= OCCUPIED_THRESHOLD)


def xy_to_cell(x: float, y: float, resolution: float, height: int, width: int) -> tuple[int, int]:
    """The environment cell (row, col) holding map-frame point (x, y), grid at the origin.

    Raises:
        ValueError: a coordinate is not finite or lies outside the ``height`` x ``width`` grid.
    """
    return GridGeometry(height, width, resolution).xy_to_cell(x, y)
