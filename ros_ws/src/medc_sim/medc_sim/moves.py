"""Collecting the team's moves for one step, with every check a move must pass (no ROS here)."""

from __future__ import annotations

import math

from medc_common.contract import agent_index


class MoveRejected(ValueError):
    """A move message that the simulator drops; the message says why."""


class MoveBook:
    """The moves received for the step that is waiting for them."""

    def __init__(self, num_agents: int, num_actions: int) -> None:
        self.num_agents = num_agents
        self.num_actions = num_actions
        self.episode = -1
        self.step = -1
        self.previous = (-1, -1)
        self._moves: list[int | None] = [None] * num_agents

    def open(self, episode: int, step: int) -> None:
        """Start collecting moves for (``episode``, ``step``); earlier moves are forgotten."""
        self.previous = (self.episode, self.step)
        self.episode, self.step = episode, step
        self._moves = [None] * self.num_agents

    def offer(self, agent_id: str, episode: int, step: int, action: int) -> int | None:
        """Record one agent's move; returns the agent's index.

        A repeated move for the same step (a resend) replaces the first one; one for the step
        just closed (an agent answering a re-sent step late) is ignored and returns None.

        Raises:
            MoveRejected: unknown agent, a move for another episode or step (e.g. one that has
            ended), or an action outside 0..num_actions-1.
        """
        try:
            idx = agent_index(agent_id, self.num_agents)
        except ValueError as exc:
            raise MoveRejected(str(exc)) from exc
        if (episode, step) == self.previous and (episode, step) != (self.episode, self.step):
            return None
        if (episode, step) != (self.episode, self.step):
            raise MoveRejected(
                f"move from {agent_id} for episode {episode} step {step}, but the simulator is at "
                f"episode {self.episode} step {self.step}"
            )
        bad_float = isinstance(action, float) and not math.isfinite(action)
        if bad_float or not 0 <= int(action) < self.num_actions:
            raise MoveRejected(f"move from {agent_id}: action {action} is not in 0..{self.num_actions - 1}")
        self._moves[idx] = int(action)
        return idx

    @property
    def complete(self) -> bool:
        """Every agent has moved."""
        return all(m is not None for m in self._moves)

    @property
    def missing(self) -> list[int]:
        """Indices of the agents that have not moved yet."""
        return [i for i, m in enumerate(self._moves) if m is None]

    def actions(self) -> list[int | None]:
        """The moves so far, ``None`` for an agent that has not moved."""
        return list(self._moves)
