"""Collecting the team's moves for one step, with every check a move must pass (no ROS here).

Moves are idempotent (docs/ros-reference.md, "Moves are executed once"): each (agent, episode, step) is
executed once, with the first move received for it. A second move for the same key from the same
sender (``AgentMove.sender``, the agent node's per-run id) is a re-send and is ignored (with another
action it is reported: :class:`ConflictingMove`); one from another sender means two processes claim
the same agent id (:class:`DuplicateAgent`). An agent that
has not moved within the simulator's move timeout is taken out (:meth:`MoveBook.take_out`): later
steps do not wait for it until a move from it is *received after* the take-out: an executed move for
the step being collected, or a move for the step collected before it (from the sender whose move
was executed for that step, or any sender if none was). The moves received before the take-out
never bring it back (docs/ros-reference.md, "A lost UAV", states the rule step by step).
"""

from __future__ import annotations

import math

from medc_common.contract import agent_index


class MoveRejected(ValueError):
    """A move message that the simulator drops; the message says why."""


class DuplicateAgent(MoveRejected):
    """Two senders answered the same (agent, episode, step): two processes claim one agent id."""


class ConflictingMove(MoveRejected):
    """One sender answered the same (agent, episode, step) twice with different actions: the first is
    executed, the second ignored (an agent's re-send is the same message)."""


class MoveBook:
    """The moves received for the step that is waiting for them."""

    def __init__(self, num_agents: int, num_actions: int) -> None:
        self.num_agents = num_agents
        self.num_actions = num_actions
        self.episode = -1
        self.step = -1
        self.previous = (-1, -1)
        self._moves: list[int | None] = [None] * num_agents
        self._senders: list[str | None] = [None] * num_agents
        self._previous_senders: list[str | None] = [None] * num_agents
        self._previous_moves: list[int | None] = [None] * num_agents
        #: Agents taken out (no move within the move timeout): steps do not wait for them.
        self.lost: set[int] = set()
        #: Every sender that has had a move executed, per agent index.
        self.known: list[set[str]] = [set() for _ in range(num_agents)]
        #: Agents that came back (a move after being taken out) since the caller last cleared it.
        self.returned: list[int] = []
        #: Re-sent moves ignored (same sender, same key).
        self.resent = 0
        #: Second moves of one sender for one key with another action, ignored.
        self.conflicts = 0

    def open(self, episode: int, step: int) -> None:
        """Start collecting moves for (``episode``, ``step``); earlier moves are forgotten."""
        self.previous = (self.episode, self.step)
        self.episode, self.step = episode, step
        self._previous_senders = self._senders
        self._previous_moves = self._moves
        self._moves = [None] * self.num_agents
        self._senders = [None] * self.num_agents

    def offer(self, agent_id: str, episode: int, step: int, action: int, sender: str = "") -> int | None:
        """Record one agent's move; returns the agent's index, or None for a move that is not
        executed: a re-send of a move already recorded for this step (same sender), or a late
        answer for the step just closed.

        Raises:
            DuplicateAgent: another sender already moved this agent in this step (or the previous
            one): the first move stands.
            MoveRejected: unknown agent, a move for another episode or step (e.g. one that has
            ended), or an action outside 0..num_actions-1.
        """
        try:
            idx = agent_index(agent_id, self.num_agents)
        except ValueError as exc:
            raise MoveRejected(str(exc)) from exc
        who = f"{agent_id} (sender {sender or '(none)'})"
        if (episode, step) == self.previous and (episode, step) != (self.episode, self.step):
            first = self._previous_senders[idx]
            if first is not None and sender != first:
                raise DuplicateAgent(
                    f"{agent_id} answered episode {episode} step {step} from two senders ({first}, "
                    f"{sender or '(none)'}): two processes claim {agent_id}; the first move was executed")
            self._conflict(idx, agent_id, episode, step, action, sender, self._previous_moves[idx], "was")
            self._came_back(idx)
            return None
        if (episode, step) != (self.episode, self.step):
            unknown = sender not in self.known[idx]
            raise MoveRejected(
                f"move from {who} for episode {episode} step {step}, but the simulator is at "
                f"episode {self.episode} step {self.step}"
                + (f"; {sender or '(none)'} never moved {agent_id} here: another graph on this "
                   "ROS_DOMAIN_ID and namespace?" if unknown and self.known[idx] else ""))
        bad_float = isinstance(action, float) and not math.isfinite(action)
        if bad_float or not 0 <= int(action) < self.num_actions:
            raise MoveRejected(f"move from {who}: action {action} is not in 0..{self.num_actions - 1}")
        if self._moves[idx] is not None:
            first = self._senders[idx]
            if sender != first:
                raise DuplicateAgent(
                    f"{agent_id} answered episode {episode} step {step} from two senders ({first}, "
                    f"{sender or '(none)'}): two processes claim {agent_id}; the first move is executed")
            self._conflict(idx, agent_id, episode, step, action, sender, self._moves[idx], "is")
            self.resent += 1
            return None  # a re-send: executed once
        self._moves[idx] = int(action)
        self._senders[idx] = sender
        self.known[idx].add(sender)
        self._came_back(idx)
        return idx

    def _conflict(self, idx: int, agent_id: str, episode: int, step: int, action, sender: str,
                  first: int | None, tense: str) -> None:
        """Raise ConflictingMove when ``action`` differs from the ``first`` one of the same sender."""
        if first is None or action == first:
            return
        self.conflicts += 1
        raise ConflictingMove(
            f"{agent_id} (sender {sender or '(none)'}) sent two moves for episode {episode} step {step} with "
            f"different actions ({first}, then {action}): the first ({first}) {tense} "
            "executed, the second ignored; an agent must re-send the same move")

    def _came_back(self, idx: int) -> None:
        if idx in self.lost:
            self.lost.discard(idx)
            self.returned.append(idx)

    def take_out(self, indices: list[int]) -> None:
        """Stop waiting for agents ``indices`` (they stay in place) until they move again."""
        self.lost.update(indices)

    @property
    def answered(self) -> int:
        """How many agents have moved in this step."""
        return sum(m is not None for m in self._moves)

    @property
    def complete(self) -> bool:
        """Every agent still in the team has moved (and at least one agent has)."""
        done = all(m is not None or i in self.lost for i, m in enumerate(self._moves))
        return done and (self.answered > 0 or len(self.lost) < self.num_agents)

    @property
    def missing(self) -> list[int]:
        """Indices of the agents that have not moved yet (those taken out included)."""
        return [i for i, m in enumerate(self._moves) if m is None]

    def actions(self) -> list[int | None]:
        """The moves so far, ``None`` for an agent that has not moved."""
        return list(self._moves)
