"""What one agent takes from a team message, checked (no ROS here): stamps, poses, readings and maps.

Poses are in the ``map`` frame (REP 103: x east, y north) and are turned into cells with the grid
geometry of the map (``info.origin``, ``info.resolution``; ``medc_common.contract.GridGeometry``).
Each check raises ``ValueError`` with the reason; the agent node logs it and drops the message.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from medc_common.contract import (
    MAP_FRAME,
    OCCUPIED_THRESHOLD,
    GridGeometry,
    geometry_of,
    occupancy_to_walls,
)

#: Default edge tolerance (cells): a pose at most this far outside the grid snaps to the edge cell.
EDGE_TOLERANCE_CELLS = 0.5


def stamp_key(stamp) -> int:
    """A builtin_interfaces/Time as integer nanoseconds (the key that ties a step together)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def walls_from_grid(msg, height: int, width: int) -> torch.Tensor:
    """bool [H,W] walls (environment rows, row 0 = north) of a nav_msgs/OccupancyGrid: a cell is a
    wall when its value is >= 50 (contract.OCCUPIED_THRESHOLD); 0..49 and -1 (unknown) are free.
    Message row j is environment row H - 1 - j (contract.occupancy_to_walls).

    Raises:
        ValueError: another frame, dimensions differ from ``height`` x ``width``, the data has the
        wrong size or values outside -1..100.
    """
    if msg.header.frame_id != MAP_FRAME:
        raise ValueError(f"map in frame {msg.header.frame_id!r}, expected {MAP_FRAME!r}")
    w, h = int(msg.info.width), int(msg.info.height)
    if (h, w) != (height, width):
        raise ValueError(f"map is {h}x{w}, this agent works on a {height}x{width} grid")
    cells = np.asarray(msg.data, dtype=np.int16)
    if cells.shape != (h * w,):
        raise ValueError(f"map data has {cells.size} cells, expected {h}x{w} = {h * w}")
    if cells.size and (cells.min() < -1 or cells.max() > 100):
        raise ValueError("map cells must be -1 (unknown), 0..100 (occupancy percent)")
    return torch.from_numpy(occupancy_to_walls(cells, h, w))


def check_wall_segments(walls: torch.Tensor, most: int) -> None:
    """Check that bool ``walls`` [H,W] are at most ``most`` straight wall segments, one cell thick,
    that the realistic sensing model's exact line-of-sight rule can take as one rectangle each
    (``tl_sensing.wall_rectangles``: a segment starts at a wall cell with no wall above or to its
    left and runs right or down), as the environment places them (segments that never touch).

    Raises:
        ValueError: more segments, or wall cells that are not such segments (an L, a T, a block).
    """
    from medc_training.envs.tl_sensing import wall_rectangles

    rects = wall_rectangles(walls.unsqueeze(0), walls.numel())[0]
    rects = rects[rects[:, 2] > rects[:, 0]]
    if len(rects) > most:
        raise ValueError(f"map has {len(rects)} wall segments; this agent's grid takes at most {most}")
    h, w = walls.shape
    rows = torch.arange(h, dtype=torch.float32).view(1, h, 1)
    cols = torch.arange(w, dtype=torch.float32).view(1, 1, w)
    r = rects.view(-1, 4, 1, 1)
    covered = ((rows > r[:, 0]) & (rows < r[:, 2]) & (cols > r[:, 1]) & (cols < r[:, 3])).sum(0)
    if bool((covered != walls.to(covered.dtype)).any()):
        raise ValueError("map walls must be straight segments one cell thick that do not touch each other "
                         "(an L, a T or a block is not): the realistic sensing model's line of sight "
                         "takes each as one rectangle")


def check_obstructions(walls: torch.Tensor) -> None:
    """Check that the blocked cells of bool ``walls`` [H,W] take at most ``OBSTRUCTION_SLOTS``
    rectangles to cover (``medc_training.envs.wall_cover``: obstructions with a free cell between
    them take one each).

    Raises:
        ValueError: more, saying how many and what to publish instead.
    """
    from medc_training.envs.wall_cover import OBSTRUCTION_SLOTS, cover_cells

    count = len(cover_cells(walls.numpy()))
    if count > OBSTRUCTION_SLOTS:
        raise ValueError(f"map obstructions take {count} rectangles to cover, more than the "
                         f"{OBSTRUCTION_SLOTS} the benchmark's world allows: publish fewer obstructions, or "
                         "ones with a free cell between them (one rectangle each)")


def faint_cells(msg) -> int:
    """How many cells of an OccupancyGrid hold 1..49: free by the contract's threshold, but maybe
    walls a driver meant (e.g. published as 1)."""
    cells = np.asarray(msg.data, dtype=np.int16)
    return int(((cells > 0) & (cells < OCCUPIED_THRESHOLD)).sum())


def xy_from_pose(msg) -> tuple[float, float]:
    """Map-frame (x, y) of a geometry_msgs/PoseStamped (z and orientation are ignored).

    Raises:
        ValueError: wrong frame or non-finite position.
    """
    if msg.header.frame_id != MAP_FRAME:
        raise ValueError(f"pose in frame {msg.header.frame_id!r}, expected {MAP_FRAME!r}")
    x, y = float(msg.pose.position.x), float(msg.pose.position.y)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"position ({x}, {y}) is not finite")
    return x, y


def pose_refusals(xy: tuple[float, float], geometries, edge_tolerance: float) -> list[ValueError] | None:
    """None when ``xy`` lies on one of ``geometries`` (within ``edge_tolerance`` cells outside its
    edge), else each geometry's reason for refusing it, in order ([] when there is none)."""
    refusals = []
    for geometry in geometries:
        try:
            geometry.xy_to_cell(*xy, edge_tolerance * geometry.resolution)
            return None
        except ValueError as exc:
            refusals.append(exc)
    return refusals


def show_stamp(key: int) -> str:
    """A stamp key (integer ns) as ``sec.nanosec`` seconds."""
    return f"{key // 1_000_000_000}.{key % 1_000_000_000:09d}"


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


def map_from_message(msg, grid: int, any_grid: bool, observation: str, exact: bool,
                     resolution: float = 0.0,
                     obstructions: bool = False) -> tuple[torch.Tensor, GridGeometry]:
    """(walls bool [H,W], geometry) of a nav_msgs/OccupancyGrid an agent working on a ``grid`` x
    ``grid`` area can play: that size, or, when its ``observation`` (a name, for the message) does
    not depend on the grid's size (``any_grid``), any square of 5 to MAX_BUNDLE_GRID cells. ``exact``:
    the sensing preset's line of sight takes each wall as one rectangle (:func:`check_wall_segments`).
    ``resolution``: metres per cell the map must have; 0 = whatever it says. ``obstructions``: the
    walls are solid obstructions that may touch (the benchmark's world, :func:`check_obstructions`)
    instead of wall segments.

    Raises:
        ValueError: a size, frame, wall layout or resolution the agent cannot play, with the reason.
    """
    from medc_training.envs.target_localization import max_walls

    size = (int(msg.info.height), int(msg.info.width))
    if size != (grid, grid) and any_grid:
        from medc_training.bundle import MAX_BUNDLE_GRID

        if size[0] != size[1] or not 5 <= size[0] <= MAX_BUNDLE_GRID:
            raise ValueError(f"map is {size[0]}x{size[1]}: the team works on square grids of 5x5 to "
                             f"{MAX_BUNDLE_GRID}x{MAX_BUNDLE_GRID} cells")
        side = size[0]
    elif size != (grid, grid):
        raise ValueError(f"map is {size[0]}x{size[1]}, but this agent's observation "
                         f"'{observation}' shows the whole {grid}x{grid} "
                         "grid its policy was trained on: publish a map of that size, or run a "
                         "policy with an agent-centred observation (egoR), which plays any size")
    else:
        side = grid
    walls = walls_from_grid(msg, side, side)
    if obstructions:
        check_obstructions(walls)
    elif exact:
        check_wall_segments(walls, max(1, max_walls(side)))
    geometry = geometry_of(msg)
    if resolution > 0 and abs(geometry.resolution - resolution) > 1e-9 * resolution:
        raise ValueError(f"map resolution is {geometry.resolution:g} m, this agent's 'resolution' "
                         f"parameter is {resolution:g} m")
    return walls, geometry
