"""Which team step an agent answers, from the driver's episode statuses (no ROS here).

Messages of one team step share one header stamp; an ``EpisodeStatus`` names the step and the walls
map that holds (its ``info.map_load_time``). Episodes (docs/ros-reference.md, "Episodes and restarts"): a
status starts a new episode (the memory is reset) when its ``step`` is 0 (and it is not a re-send
of the step-0 status already answered: same stamp), or its ``episode`` or ``map_stamp`` differs
from the episode in memory. So a driver that restarts (episode 0 step 0 again, a new map) is
followed at once. Within one episode on one map a status for an older step is dropped, and one for
the step already answered is a re-send.
"""

from __future__ import annotations

from dataclasses import dataclass

from medc_agents.team_messages import show_stamp, stamp_key


@dataclass(frozen=True)
class Tick:
    """One team step the agent must answer."""

    episode: int
    step: int
    stamp: int
    map_stamp: int


class EpisodeClock:
    """The step last answered (the episode in memory), the step waiting for its inputs, and when
    the memory must start afresh."""

    def __init__(self) -> None:
        #: The step last observed: episode, step, header stamp and map (stamp keys); -1 = none.
        self.episode = -1
        self.step = -1
        self.stamp = -1
        self.map = -1
        #: The status taken last that was not answered yet, if any.
        self.pending: Tick | None = None
        self._force_start = False
        #: Whether the memory holds an episode (it has been started once).
        self.started = False

    def answered(self, t: Tick) -> bool:
        """``t`` is the step already observed (and so decided): same episode, map and step (and,
        for step 0, the same stamp: a step 0 with a new stamp is a new start)."""
        same = (t.episode, t.map_stamp, t.step) == (self.episode, self.map, self.step)
        return same and (t.step != 0 or t.stamp == self.stamp)

    def open_tick(self) -> Tick | None:
        """The pending step if it has not been answered yet."""
        t = self.pending
        return None if t is None or self.answered(t) else t

    def maps_in_use(self) -> tuple[int | None, int]:
        """The map stamps the pending step (None without one) and the episode in memory name."""
        return (self.pending.map_stamp if self.pending is not None else None), self.map

    def take_status(self, msg, ids: list[str]) -> Tick | None:
        """Take an EpisodeStatus for team ``ids``; returns the tick to answer, or None (episode end).

        The returned tick may be one already answered (:meth:`answered`): a re-sent step.

        Raises:
            ValueError: the status lists another team, or is for an older step of the episode
            being played (same episode and map, a lower step other than 0).
        """
        if list(msg.agent_ids) != ids:
            raise ValueError(f"status lists agents {list(msg.agent_ids)}, this team is {ids}")
        if msg.done:
            return None
        tick = Tick(int(msg.episode), int(msg.step), stamp_key(msg.header.stamp), stamp_key(msg.map_stamp))
        same_episode = (tick.episode, tick.map_stamp) == (self.episode, self.map)
        if same_episode and 0 < tick.step < self.step:
            raise ValueError(
                f"status for episode {tick.episode} step {tick.step} is older than the one answered "
                f"(episode {self.episode} step {self.step}, same map)"
            )
        if not self.answered(tick):
            self.pending = tick
        return tick

    def restart(self) -> None:
        """Take the next step as the start of an episode in memory (the agent follows the driver
        again after answering a step that was not the driver's)."""
        self.step = -1
        self._force_start = True

    def advance(self, t: Tick) -> tuple[bool, str | None]:
        """Record ``t`` as answered. Returns (whether the memory starts afresh at ``t``, a note to
        log when the driver went back to an earlier step without being told to restart)."""
        fresh = (t.episode, t.map_stamp) != (self.episode, self.map) or t.step == 0
        if self._force_start:
            fresh, self._force_start = True, False
            self.started = False
        note = None
        if fresh or not self.started:
            fresh = True
            if self.started and (t.episode, t.step) <= (self.episode, self.step):
                note = (f"episode status went back from episode {self.episode} step {self.step} to "
                        f"episode {t.episode} step {t.step} (map_load_time {show_stamp(self.map)} -> "
                        f"{show_stamp(t.map_stamp)}): the driver restarted; memory reset, following it")
            self.started = True
        self.episode, self.step, self.stamp, self.map = t.episode, t.step, t.stamp, t.map_stamp
        return fresh, note
