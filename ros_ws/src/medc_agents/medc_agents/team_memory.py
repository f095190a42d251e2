"""The team memory one agent keeps and the observation it builds from it (no ROS here).

The agent keeps the same memory the training environment keeps (latest normalised reading and
visit count per cell, and the team's source posterior: ``medc_training.envs.tl_observation``
TeamMemory) and turns it into the observation its policy takes with the very builder the
environment uses (``tl_observation.observe`` and the grid module's move mask), so a policy sees in
ROS exactly what it saw in training. The memory holds everything any observation variant needs,
so a policy swap to a model that takes another variant keeps the episode's history.

In the field benchmark's world the walls are solid obstructions that may touch: the memory starts
each episode from the map's exact cover by rectangles (``medc_training.envs.wall_cover``), whose line
of sight is the one of the obstructions' own rectangles.
"""

from __future__ import annotations

import torch


class AgentMemory:
    """The team memory on a ``grid`` x ``grid`` area under a ``sensing`` preset (a parsed
    ``tl_sensing`` model), and the team's last observed step."""

    def __init__(self, grid: int, sensing, rule_out: bool = True, world: str = "grid") -> None:
        """``rule_out``: cells the team stood on without the episode ending are not the source
        (``SourceEstimator``'s ``rule_out``); ``world``: ``grid`` (wall segments) or ``radbench``
        (obstructions, covered by rectangles)."""
        from medc_training.envs.grid import action_deltas

        self.sensing = sensing
        self.rule_out = bool(rule_out)
        self.world = world
        self._deltas = action_deltas("cpu")
        self.resize(grid)
        #: The last observed step: every agent's cell int64 [1,N,2], the walls bool [1,G,G] and
        #: every agent's move mask bool [1,N,A]; what a controller decides from.
        self.positions: torch.Tensor | None = None
        self.walls: torch.Tensor | None = None
        self.team_mask: torch.Tensor | None = None

    @property
    def grid(self) -> int:
        """The side of the area the memory covers."""
        return self.memory.grid

    def resize(self, grid: int) -> None:
        """Work on a ``grid`` x ``grid`` area from now on: a fresh memory of that size."""
        from medc_training.envs.target_localization import max_walls
        from medc_training.envs.tl_observation import ObservationSpec, TeamMemory
        from medc_training.envs.wall_cover import OBSTRUCTION_SLOTS

        #: Most rectangles a map may take (the exact line-of-sight rule keeps one per wall segment):
        #: as many segments as the environment places on this grid, or in the benchmark's world the
        #: rectangles of its obstructions' cover (``wall_cover.OBSTRUCTION_SLOTS``).
        self.max_walls = OBSTRUCTION_SLOTS if self.world == "radbench" else max(1, max_walls(int(grid)))
        self.memory = TeamMemory(ObservationSpec("maps", 0, True), 1, int(grid), "cpu", sensing=self.sensing,
                                 max_walls=self.max_walls, rule_out=self.rule_out)

    def record(self, walls: torch.Tensor, positions: torch.Tensor, readings: torch.Tensor,
               fresh: bool) -> None:
        """Fold the readings float32 [1,K] taken at ``positions`` int64 [1,K,2] on ``walls`` bool
        [1,G,G] into the memory; ``fresh``: they start an episode (the memory is reset, and resized
        to the map's grid)."""
        if fresh:
            if walls.shape[-1] != self.memory.grid:
                self.resize(walls.shape[-1])
            rects = None
            if self.world == "radbench":
                from medc_training.envs.wall_cover import cover_rectangles

                rects = cover_rectangles(walls, self.max_walls)
            self.memory.start(walls, positions, readings, rects=rects)
        else:
            self.memory.record(walls, positions, readings)

    def observe(self, observation, positions: torch.Tensor, walls: torch.Tensor,
                index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Agent ``index``'s observation [C,H,W] (``observation``: a parsed variant) and move mask
        [A] with the team at ``positions`` int64 [1,N,2] on ``walls`` bool [1,G,G]."""
        from medc_training.envs.grid import move_mask, pad_blocked

        obs = self.memory.observe_agent(positions, walls, index, observation)
        team_mask = move_mask(positions, pad_blocked(walls), self._deltas)
        self.positions, self.walls, self.team_mask = positions, walls, team_mask
        return obs[0], team_mask[0, index]
