"""Building the simulator's messages from the world state (plain functions, no node needed)."""

from __future__ import annotations

import torch
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from medc_common import contract
from medc_interfaces.msg import EpisodeStatus, RadiationReading
from nav_msgs.msg import OccupancyGrid

from medc_sim.sim_core import EpisodeResult

OCCUPIED = contract.OCCUPIED


def grid_msg(walls: torch.Tensor, stamp: Time, resolution: float) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid of bool ``walls`` [H,W] (environment rows, row 0 = north), origin at
    (0, 0) of the map frame with identity orientation: environment cell (row, col) is message cell
    (i = col, j = H - 1 - row), ``data[j * W + i]`` (contract.walls_to_occupancy)."""
    grid = OccupancyGrid()
    grid.header.stamp = stamp
    grid.header.frame_id = contract.MAP_FRAME
    grid.info.map_load_time = stamp
    grid.info.resolution = float(resolution)
    h, w = walls.shape
    grid.info.width, grid.info.height = int(w), int(h)
    grid.info.origin.orientation.w = 1.0
    grid.data = contract.walls_to_occupancy(walls.cpu())
    return grid


def pose_msg(cell: tuple[int, int], stamp: Time, geometry: contract.GridGeometry) -> PoseStamped:
    """geometry_msgs/PoseStamped at the centre of environment ``cell`` (row, col), frame "map"
    (REP 103: x east, y north), on the grid ``geometry`` describes."""
    pose = PoseStamped()
    pose.header.stamp = stamp
    pose.header.frame_id = contract.MAP_FRAME
    pose.pose.position.x, pose.pose.position.y = geometry.cell_to_xy(cell[0], cell[1])
    pose.pose.orientation.w = 1.0
    return pose


def reading_msg(agent_id: str, value: float, variance: float, stamp: Time) -> RadiationReading:
    """medc_interfaces/RadiationReading of one agent."""
    reading = RadiationReading()
    reading.header.stamp = stamp
    reading.header.frame_id = contract.MAP_FRAME
    reading.agent_id = agent_id
    reading.value = float(value)
    reading.variance = float(variance)
    return reading


def status_msg(
    ids: list[str], episode: int, step: int, stamp: Time, map_stamp: Time,
    result: EpisodeResult | None = None, session: str = "",
) -> EpisodeStatus:
    """medc_interfaces/EpisodeStatus: a step to answer, or (``result`` given) an episode's end;
    ``session``: the driver's per-run id."""
    status = EpisodeStatus()
    status.session = session
    status.header.stamp = stamp
    status.header.frame_id = contract.MAP_FRAME
    status.episode, status.step = int(episode), int(step)
    status.map_stamp = map_stamp
    status.agent_ids = list(ids)
    if result is not None:
        status.done, status.success, status.truncated = True, result.success, result.truncated
        status.episode_length = result.length
        status.reward = result.reward
    return status
