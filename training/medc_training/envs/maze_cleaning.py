"""Multi-agent maze cleaning (paper Section V-D).

Agents clean every free cell of a random binary-tree maze on a G x G grid (``complexity``: the share
of the walls between rooms that are kept); the team is rewarded per cell cleaned and pays a time
cost per step. Each agent sees 4 maps (:data:`CHANNELS`); the oracle scores each move by the BFS
distance to the nearest dirty cell, recomputed on every call since the dirt changes every step.
The maze, moves, rewards and observation: docs/environments.md, "Maze cleaning".
"""

from __future__ import annotations

from typing import Any

import torch

from medc_training.envs.core import MapsObservationEnv, check_bool, check_core_options, maps_channels
from medc_training.envs.descriptor import Application, register
from medc_training.envs.grid import (
    ACTIONS,
    action_deltas,
    bfs_distance,
    neighbour_index,
    pad_blocked,
    random_free_cells,
)
from medc_training.envs.names import MAZE_CLEANING

__all__ = [
    "APPLICATION",
    "CHANNELS",
    "CLEAN_REWARD",
    "TIME_COST",
    "MazeCleaning",
    "build_maze_observations",
    "generate_mazes",
]

CLEAN_REWARD = 1.0
TIME_COST = 0.1
CHANNELS: tuple[str, ...] = ("own_location", "team_locations", "dirty_cells", "walls")


def generate_mazes(
    count: int, grid: int, complexity: float, generator: torch.Generator, device: torch.device
):
    """bool [count,G,G] wall maps of random binary-tree mazes (see the module docstring)."""
    r = torch.arange(grid, device=device).view(grid, 1)
    c = torch.arange(grid, device=device).view(1, grid)
    room = (r % 2 == 0) & (c % 2 == 0)
    between = (r % 2) != (c % 2)  # wall cells that separate two rooms (or a room and the edge)
    walls = (~room).expand(count, grid, grid).clone()
    north = torch.rand((count, grid, grid), generator=generator, device=device) < 0.5
    north = (north | (c == 0)) & (r > 0)  # top edge: west; left edge: north
    west = ~north & (c > 0)
    # A room at (r, c) opens (r - 1, c) or (r, c - 1): shift the choices onto those cells.
    open_cells = torch.zeros_like(walls)
    open_cells[:, :-1, :] |= (north & room)[:, 1:, :]
    open_cells[:, :, :-1] |= (west & room)[:, :, 1:]
    walls &= ~open_cells
    if complexity < 1.0:
        drop = torch.rand((count, grid, grid), generator=generator, device=device) >= complexity
        walls &= ~(drop & between)
    return walls


def build_maze_observations(
    positions: torch.Tensor, dirty: torch.Tensor, walls: torch.Tensor
) -> torch.Tensor:
    """Every agent's 4-map observation, float32 [B,N,4,G,G] (channels: :data:`CHANNELS`).

    positions int64 [B,N,2]; dirty bool [B,G,G]; walls bool [B,G,G].
    """
    b, n = positions.shape[:2]
    g = walls.shape[-1]
    dev = positions.device
    cell = positions[..., 0] * g + positions[..., 1]
    out = torch.empty((b, n, len(CHANNELS), g * g), dtype=torch.float32, device=dev)
    own = torch.zeros((b, n, g * g), device=dev).scatter_(2, cell.unsqueeze(2), 1.0)
    out[:, :, 0] = own
    out[:, :, 1] = (own.sum(1, keepdim=True) - own).clamp_(0.0, 1.0)
    out[:, :, 2] = dirty.view(b, 1, -1)
    out[:, :, 3] = walls.view(b, 1, -1)
    return out.view(b, n, len(CHANNELS), g, g)


class MazeCleaning(MapsObservationEnv):
    """Batched maze cleaning core (rules: module docstring).

    ``make_batched("maze_cleaning", num_envs=B, device="cpu", seed=0, agents=3, grid=10,
    complexity=1.0, max_steps=100)``.
    """

    name = MAZE_CLEANING
    CHANNELS = CHANNELS
    WALL_CHANNELS = (3,)

    def __init__(
        self,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        agents: int = 3,
        grid: int = 10,
        complexity: float = 1.0,
        max_steps: int = 100,
        copy_obs: bool = True,
        observation: str = "maps",
    ) -> None:
        # At most one agent per room (the fewest free cells a maze of this size can have).
        self.grid, self.num_agents, self.max_steps = check_core_options(
            grid, agents, max_steps, grid_range=(3, 64), max_agents=lambda g: min(16, ((g + 1) // 2) ** 2)
        )
        if (
            isinstance(complexity, bool)
            or not isinstance(complexity, int | float)
            or not 0.0 <= complexity <= 1.0
        ):
            raise ValueError(f"complexity must be a number in [0, 1], got {complexity!r}")
        self.complexity = float(complexity)
        self.copy_obs = check_bool("copy_obs", copy_obs)
        super().__init__(num_envs, device, seed)
        self.num_actions = len(ACTIONS)
        self._set_observation(observation, len(self.CHANNELS))
        self._deltas = action_deltas(self.device)
        self._started = False

    @property
    def attributes(self) -> dict[str, Any]:
        return {
            "agents": self.num_agents,
            "grid": self.grid,
            "complexity": self.complexity,
            "max_steps": self.max_steps,
        }

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        k = self.num_envs if rows is None else len(rows)
        walls = generate_mazes(k, self.grid, self.complexity, self.generator, self.device)
        positions = random_free_cells(~walls, self.num_agents, self.generator)
        dirty = ~walls
        cell = positions[..., 0] * self.grid + positions[..., 1]
        dirty.view(k, -1).scatter_(1, cell, False)
        if rows is None:
            self.walls, self.positions, self.dirty = walls, positions, dirty
            self.blocked_pad = pad_blocked(walls)
            self.t = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        else:
            self.walls[rows], self.positions[rows], self.dirty[rows] = walls, positions, dirty
            self.blocked_pad[rows] = pad_blocked(walls)
            self.t[rows] = 0

    def _observe_maps(self) -> torch.Tensor:
        return build_maze_observations(self.positions, self.dirty, self.walls)

    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = self.num_envs
        cell = self.positions[..., 0] * self.grid + self.positions[..., 1]
        before = self.dirty.view(b, -1).sum(1)
        self.dirty.view(b, -1).scatter_(1, cell, False)
        left = self.dirty.view(b, -1).sum(1)
        reward = CLEAN_REWARD * (before - left).float() - TIME_COST
        success = left == 0
        return reward, success

    def oracle_action_scores(self) -> torch.Tensor:
        """float32 [B,N,A]: minus the BFS distance to the nearest dirty cell after each move."""
        b, n = self.positions.shape[:2]
        dist = bfs_distance(~self.walls, self.dirty)
        dist = torch.where(torch.isinf(dist), 0.0, dist)  # nothing dirty left: any move will do
        dist_pad = torch.nn.functional.pad(dist, (1, 1, 1, 1), value=0.0)
        idx = neighbour_index(self.positions, self.grid, self._deltas).view(b, -1)
        scores = -dist_pad.view(b, -1).gather(1, idx).view(b, n, -1)
        return torch.where(self.mask, scores, float("-inf"))


APPLICATION = register(Application(name=MazeCleaning.name, core=MazeCleaning, default_observation="maps",
                                   channels=maps_channels(CHANNELS)))
