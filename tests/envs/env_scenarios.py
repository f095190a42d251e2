"""Small scenarios of the three applications, shared by the environment tests (quick to step,
still with walls, several customers, a maze)."""

from __future__ import annotations

SMALL = {
    "target_localization": {"agents": 3, "walls": 2, "grid": 12, "max_steps": 40},
    "fleet_coordination": {"agents": 3, "customers": 4, "capacity": 2, "grid": 6, "max_steps": 40},
    "maze_cleaning": {"agents": 2, "grid": 7, "max_steps": 40},
}
