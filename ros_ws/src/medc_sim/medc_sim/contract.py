"""The topic contract between the simulator (or a real UAV driver) and the agent nodes.

Everything a node needs to agree on lives here: topic names, QoS profiles, frames, agent ids,
and the grid <-> map-frame conversion. docs/ros.md describes the same contract for people.
"""

from __future__ import annotations

import math
import re

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

MAP_FRAME = "map"
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

#: Episode results: every one kept (up to 1000) for readers that join late or fall behind.
RESULTS_QOS = QoSProfile(
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: What an agent id looks like: agent_<i>, i = the agent's index in the environment.
AGENT_ID_PATTERN = re.compile(r"^agent_(\d+)$")


def agent_ids(num_agents: int) -> list[str]:
    """The ids of a team of ``num_agents``: ``agent_0`` .. ``agent_{n-1}`` (env agent order)."""
    if num_agents < 1:
        raise ValueError(f"num_agents must be >= 1, got {num_agents}")
    return [f"agent_{i}" for i in range(num_agents)]


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


def pose_topic(namespace: str, agent_id: str) -> str:
    """geometry_msgs/PoseStamped, SENSOR_QOS: the agent's position in the map frame."""
    return f"{_ns(namespace)}/{agent_id}/pose"


def radiation_topic(namespace: str, agent_id: str) -> str:
    """medc_interfaces/RadiationReading, SENSOR_QOS: the agent's latest measurement."""
    return f"{_ns(namespace)}/{agent_id}/radiation"


def move_topic(namespace: str, agent_id: str) -> str:
    """medc_interfaces/AgentMove, RELIABLE_QOS: the move the agent's policy chose."""
    return f"{_ns(namespace)}/{agent_id}/move"


def policy_topic(namespace: str, agent_id: str) -> str:
    """std_msgs/String, LATCHED_QOS: a bundle path (or ``ipfs://``/CID via the bridge) to run."""
    return f"{_ns(namespace)}/{agent_id}/policy"


def team_policy_topic(namespace: str) -> str:
    """std_msgs/String, LATCHED_QOS: a bundle path every agent of the team switches to."""
    return f"{_ns(namespace)}/team/policy"


def map_topic(namespace: str) -> str:
    """nav_msgs/OccupancyGrid, LATCHED_QOS: the walls of the current episode (100 = wall)."""
    return f"{_ns(namespace)}/map"


def status_topic(namespace: str) -> str:
    """medc_interfaces/EpisodeStatus, RELIABLE_QOS: one per team step, after poses and readings."""
    return f"{_ns(namespace)}/episode"


def results_topic(namespace: str) -> str:
    """medc_interfaces/EpisodeStatus, RESULTS_QOS: the closing status (done) of every episode."""
    return f"{_ns(namespace)}/episode_result"


def cell_to_xy(row: int, col: int, resolution: float) -> tuple[float, float]:
    """Centre of grid cell (row, col) in the map frame: x along columns, y along rows."""
    return (col + 0.5) * resolution, (row + 0.5) * resolution


def xy_to_cell(x: float, y: float, resolution: float, height: int, width: int) -> tuple[int, int]:
    """The grid cell (row, col) holding map-frame point (x, y).

    Raises:
        ValueError: a coordinate is not finite or lies outside the ``height`` x ``width`` grid.
    """
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"position ({x}, {y}) is not finite")
    col, row = math.floor(x / resolution), math.floor(y / resolution)
    if not (0 <= row < height and 0 <= col < width):
        raise ValueError(
            f"position ({x:.3f}, {y:.3f}) m is outside the {height}x{width} grid (resolution {resolution} m)"
        )
    return row, col
