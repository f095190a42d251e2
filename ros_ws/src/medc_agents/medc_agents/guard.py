"""What an agent does not take on trust (no ROS here): lost teammates, other drivers' statuses,
statuses that jump ahead, maps that contradict the team's poses, readings in the wrong units.

docs/ros-reference.md, "A lost UAV" and "Messages that contradict the team's evidence", state the rules;
the agent node applies them with these classes and reports what they say on ``/diagnostics``.

- :class:`LostWatch`: a teammate whose pose or reading for the step being waited on has not come
  for ``lost_timeout_s`` (and nothing of that kind came from it meanwhile) is taken out of the team;
  the agent decides without it (its last cell stays in the observation, no reading of it is
  recorded) until its pose and reading come again.
- :class:`StatusGate`: statuses of one driver session at a time; a status from another session
  while the followed one still publishes is held (a second graph on the domain); a status that
  jumps more than one step ahead within the episode is held until the driver confirms it; statuses
  below the answered step that keep coming for ``recover_s`` mean the answered step was not the
  driver's: the agent follows the driver again.
- :class:`ReadingCheck`: readings outside what the sensor model can produce, warned once per
  agent and kind.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

#: Default of the agent's ``lost_timeout_s``: a teammate silent this long is taken out. Shorter than
#: a driver's move timeout (the simulator's ``move_timeout_s``, 3 s) so the team answers before the
#: driver gives up on it.
LOST_TIMEOUT_S = 1.5
#: Default of ``session_hold_s``: a new driver session is followed once the old one has been silent
#: this long (a restarted driver); before that its statuses are held (a second driver).
SESSION_HOLD_S = 1.0
#: Default of ``recover_s``: how long held or contradicting evidence must persist before the agent
#: follows the driver's statuses again (the longest a hostile status can hold a team up).
RECOVER_S = 2.0
#: A reading above this many times the sensor model's highest rate is not from this model.
HIGH_FACTOR = 4.0
#: Readings per agent whose mean is compared with the lowest background.
LOW_WINDOW = 8


class LostWatch:
    """Which teammates are out of the team (see the module docstring)."""

    def __init__(self, num_agents: int, own: int, timeout_s: float = LOST_TIMEOUT_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.num_agents = num_agents
        self.own = own
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self.arrived: dict[tuple[str, int], float] = {}
        self.lost: dict[int, str] = {}  # index -> why

    def seen(self, kind: str, idx: int) -> None:
        """A valid pose or reading of agent ``idx`` arrived."""
        self.arrived[(kind, idx)] = self.clock()

    def check(self, missing: dict[int, list[str]], waiting_since: float,
              fresh: set[int] | frozenset = frozenset()) -> list[tuple[int, str]]:
        """Teammates newly lost: ``missing`` maps an agent index to the kinds ('pose', 'reading')
        the step being waited on (since ``waiting_since``, clock time) still lacks from it;
        ``fresh``: agents that sent something newer than the last step answered (alive, if
        mis-stamped: a stall to report, not a lost UAV)."""
        if self.timeout_s <= 0:
            return []
        now = self.clock()
        newly = []
        for idx, kinds in missing.items():
            if idx == self.own or idx in self.lost or idx in fresh:
                continue
            for kind in kinds:
                last = max(self.arrived.get((kind, idx), waiting_since), waiting_since)
                if now - last >= self.timeout_s:
                    heard = self.arrived.get((kind, idx))
                    ago = "never" if heard is None else f"{now - heard:.1f} s ago"
                    self.lost[idx] = f"no {kind} for {now - last:.1f} s (last one {ago})"
                    newly.append((idx, self.lost[idx]))
                    break
        return newly

    def back(self, idx: int) -> bool:
        """Agent ``idx`` is heard from again (pose and reading of one step); True if it was lost."""
        return self.lost.pop(idx, None) is not None


class StatusGate:
    """Decides which EpisodeStatus messages an agent obeys (see the module docstring).

    :meth:`admit` returns ``(verdict, reason)``: ``take`` (hand it to the observer), ``restart``
    (hand it over as the start of a new episode in memory: the agent follows the driver again),
    ``drop`` (the observer would refuse it; the reason says why) or ``hold`` (kept aside and
    reported; :attr:`held` holds it).
    """

    def __init__(self, session_hold_s: float = SESSION_HOLD_S, recover_s: float = RECOVER_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.session_hold_s = float(session_hold_s)
        self.recover_s = float(recover_s)
        self.clock = clock
        self.session: str | None = None
        self.last_seen = 0.0
        #: Other sessions heard while following one: session -> clock time last heard.
        self.foreign: dict[str, float] = {}
        self.held = None  # (msg, since)
        self._older_since: float | None = None

    def admit(self, msg, mem_episode: int, mem_map: int, mem_step: int, map_key: int) -> tuple[str, str]:
        now = self.clock()
        session = str(msg.session)
        if self.session is None:
            self.session = session
        elif session != self.session:
            if now - self.last_seen < self.session_hold_s:
                self.foreign[session] = now
                return "hold", (
                    f"status from driver session {session or '(none)'!r} (episode {msg.episode} step "
                    f"{msg.step}) while session {self.session or '(none)'!r} is publishing (its last status "
                    f"{now - self.last_seen:.1f} s ago): a second driver or graph on this ROS_DOMAIN_ID and "
                    "namespace? held; give each graph its own ROS_DOMAIN_ID or namespace")
            self.foreign.pop(session, None)
            self.session = session  # the old session fell silent: a restarted driver
            self.held = None
            self._older_since = None
        self.last_seen = now
        if msg.done or mem_step < 0 or (int(msg.episode), map_key) != (mem_episode, mem_map):
            self._older_since = None
            return "take", ""
        step = int(msg.step)
        if 0 < step < mem_step:
            if self._older_since is None:
                self._older_since = now
            if now - self._older_since >= self.recover_s:
                self._older_since = None
                self.held = None
                return "restart", (
                    f"statuses of episode {msg.episode} kept coming below step {mem_step} (the step "
                    f"answered) for {self.recover_s:g} s: that step was not this driver's; following the "
                    f"driver from step {step} (memory of the episode reset)")
            return "drop", (f"status for episode {msg.episode} step {step} is older than the one answered "
                            f"(episode {mem_episode} step {mem_step}, same map)")
        self._older_since = None
        if step > mem_step + 1:
            held = self.held
            key = (int(msg.episode), map_key, step)
            if held is not None:
                hmsg, since = held
                hkey = (int(hmsg.episode), map_key, int(hmsg.step))
                confirms = (hkey[:2] == key[:2] and hkey[2] == step - 1) or \
                           (hkey == key and now - since >= self.recover_s)
                if confirms:
                    self.held = None
                    return "take", ""
                if hkey == key:
                    return "hold", ""  # the same held status again, not yet confirmed
            self.held = (msg, now)
            return "hold", (
                f"status for episode {msg.episode} step {step} jumps ahead of the step answered "
                f"({mem_step}): held until the driver confirms it (its next step, or the same status "
                f"again after {self.recover_s:g} s); statuses for step {mem_step + 1} are answered meanwhile")
        if self.held is not None and step == mem_step + 1:
            self.held = None
        return "take", ""

    def foreign_now(self) -> list[str]:
        """Other sessions heard within the last ``recover_s`` * 5 seconds."""
        now = self.clock()
        for s in [s for s, t in self.foreign.items() if now - t > 5 * self.recover_s]:
            del self.foreign[s]
        return sorted(self.foreign)


class ReadingCheck:
    """Readings the sensor model cannot produce (wrong units, a misconfigured detector)."""

    def __init__(self, sensing, num_agents: int) -> None:
        self.high = HIGH_FACTOR * float(sensing.max_rate)
        self.low = 0.5 * float(sensing.background[0])
        self.name = sensing.name
        self.recent = [deque(maxlen=LOW_WINDOW) for _ in range(num_agents)]
        self.warned: set[tuple[int, str]] = set()

    def check(self, idx: int, agent_id: str, value: float) -> str | None:
        """A warning the first time agent ``idx``'s readings look implausible (per kind), else None.
        A kind warned is over (:attr:`warned` loses it) once the last LOW_WINDOW readings of that
        agent are plausible again."""
        recent = self.recent[idx]
        recent.append(value)
        if len(recent) == recent.maxlen:
            if (idx, "high") in self.warned and max(recent) <= self.high:
                self.warned.discard((idx, "high"))
            if (idx, "low") in self.warned and sum(recent) / len(recent) >= self.low:
                self.warned.discard((idx, "low"))
        if value > self.high and (idx, "high") not in self.warned:
            self.warned.add((idx, "high"))
            return (f"reading {value:g} of {agent_id} is above {self.high:g} counts/s, {HIGH_FACTOR:g}x the "
                    f"highest rate of the '{self.name}' sensor model: readings must be counts per second "
                    "(docs/ros-reference.md, 'Sensor model'), not scaled")
        if len(recent) == recent.maxlen and (idx, "low") not in self.warned:
            mean = sum(recent) / len(recent)
            if mean < self.low:
                self.warned.add((idx, "low"))
                return (f"the last {len(recent)} readings of {agent_id} average {mean:.4g} counts/s, "
                        f"below half the lowest background of the '{self.name}' sensor model "
                        f"({2 * self.low:g} counts/s): readings in the wrong units (normalised or "
                        "divided)? docs/ros-reference.md, 'Sensor model'")
        return None
