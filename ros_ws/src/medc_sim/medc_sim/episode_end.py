"""How the simulator ends an episode: the rule (``end_on``) and the team's declaration (no ROS here).

``end_on`` (a parameter of the simulator and a key of the launch config):

``source`` (default, the training environment's rule)
    an episode ends with success when, after the team's moves, a UAV stands within the sensing
    preset's success radius of the source; declarations are not listened to;
``declaration``
    an episode ends when the team declares the source localised (medc_interfaces/SourceDeclaration);
    it is a success when the declared cell lies within the success radius of the source. Finding the
    source does not end it (as for a real driver, which cannot know the source), so the agents must
    run with ``source_ends_episode:=false``;
``either``
    whichever comes first: the source found, or the team's declaration.

Every rule also truncates an episode after ``max_steps`` moves.
"""

from __future__ import annotations

import math

#: The simulator's end rules (``end_on``).
END_RULES = ("source", "declaration", "either")


def check_end_rule(name: object) -> str:
    """``name`` if it is one of :data:`END_RULES`.

    Raises:
        ValueError: naming the rules.
    """
    if name not in END_RULES:
        raise ValueError(f"end_on must be one of {', '.join(END_RULES)}, got {str(name)[:40]!r}")
    return str(name)


def declared_cell(cell_i: int, cell_j: int, grid: int) -> tuple[int, int]:
    """The environment cell (row, col) of a declaration's OccupancyGrid cell (i, j).

    Raises:
        ValueError: the cell lies outside the ``grid``×``grid`` map.
    """
    i, j = int(cell_i), int(cell_j)
    if not (0 <= i < grid and 0 <= j < grid):
        raise ValueError(f"declared cell (i {i}, j {j}) is outside the {grid}x{grid} map")
    return grid - 1 - j, i


def judge(cell: tuple[int, int], target: tuple[int, int], success_radius: float) -> tuple[float, bool]:
    """(distance in cells from the declared ``cell`` to the source ``target``, whether a UAV on the
    declared cell would find the source: distance within ``success_radius``)."""
    error = math.hypot(cell[0] - target[0], cell[1] - target[1])
    return error, error <= success_radius + 1e-9
