"""An agent node's watch over its team: stalls, lost and silent teammates, duplicate ids, the
driver's statuses (a second driver, statuses below the step answered), implausible readings and the
observer's notes.

Each watch is an object owned by :class:`medc_agents.node.AgentNode` and built from what it reads
and reports to (the team observer, a Health, a logger, a clock); the node hands it messages and
calls it from its watch timer. The rules themselves live in :mod:`medc_agents.guard` and the
team-state units (:mod:`medc_agents.team_state`); each watch is tested without a node too.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus
from medc_common import contract
from medc_training.untrusted import printable

from medc_agents.guard import LOW_WINDOW
from medc_agents.team_episode import Tick
from medc_agents.team_messages import show_stamp, stamp_key

#: Seconds without a repeat after which a fault that came from outside (another process moving as
#: this agent) is over: its condition is OK again.
CLEAR_S = 10.0
#: A pose or reading stamped more than this (ns) ahead of the step waited on is not a sign of life.
FUTURE_NS = 5_000_000_000

Clock = Callable[[], float]


class ClaimWatch:
    """The ``moves`` condition: another process publishing moves as this agent (a duplicate id),
    OK again after CLEAR_S seconds without one."""

    def __init__(self, agent_id: str, sender: str, health, clock: Clock = time.monotonic) -> None:
        """``sender``: this node's per-run id (AgentMove.sender); ``health``: its Health."""
        self.agent_id = agent_id
        self.sender = sender
        self.health = health
        self.clock = clock
        #: When another process last moved as this agent (None: not within CLEAR_S).
        self.claimed_at: float | None = None

    def on_move(self, msg) -> None:
        """A move heard on this agent's own move topic."""
        if msg.sender == self.sender:
            return
        self.claimed_at = self.clock()
        self.health.set("moves", DiagnosticStatus.WARN, (
            f"another process publishes moves as {self.agent_id} (sender {printable(str(msg.sender), 40)!r}; "
            f"this node is {self.sender}): two processes claim {self.agent_id}; stop one of them"))

    def check(self) -> None:
        """OK again once no other process has moved as this agent for CLEAR_S seconds."""
        if self.claimed_at is not None and self.clock() - self.claimed_at >= CLEAR_S:
            self.claimed_at = None
            self.health.set("moves", DiagnosticStatus.OK, f"no other process has moved as {self.agent_id} "
                            f"for {CLEAR_S:g} s")


class DriverWatch:
    """The ``driver`` condition: statuses from more than one driver session (a second graph)."""

    def __init__(self, gate, health, status_topic: str) -> None:
        """``gate``: the agent's guard.StatusGate; ``status_topic``: the topic named in the report."""
        self.gate = gate
        self.health = health
        self.status_topic = status_topic

    def check(self) -> None:
        foreign = self.gate.foreign_now()
        if foreign:
            self.health.set("driver", DiagnosticStatus.WARN, (
                f"statuses from {len(foreign) + 1} driver sessions on {self.status_topic} (following "
                f"{self.gate.session or '(none)'!r}, held: {', '.join(foreign)}): a second graph shares this "
                "ROS_DOMAIN_ID and namespace; give each graph its own ROS_DOMAIN_ID or namespace"))
        elif self.health.level("driver") != DiagnosticStatus.OK:
            self.health.set("driver", DiagnosticStatus.OK, "one driver session")


class StatusIntake:
    """The ``status`` condition: each episode status passes the agent's guard.StatusGate (held while
    another session is followed, dropped below the step answered, a restart of the driver taken)."""

    def __init__(self, gate, health, dropped_by: Counter, old: Callable[[str], None],
                 restart: Callable[[], None]) -> None:
        """``dropped_by``: the node's count of dropped messages by kind (a held status adds 'held
        status'); ``old``: takes a status below the step answered (OldStatuses.drop); ``restart``:
        starts the team state over (a restarted driver)."""
        self.gate = gate
        self.health = health
        self.dropped_by = dropped_by
        self.old = old
        self.restart = restart

    def admit(self, msg, clock) -> bool:
        """Whether the team state takes ``msg``; ``clock``: the team state's episode clock."""
        verdict, why = self.gate.admit(msg, clock.episode, clock.map, clock.step, stamp_key(msg.map_stamp))
        if verdict == "hold":
            self.dropped_by["held status"] += 1
            if why:
                self.health.set("status", DiagnosticStatus.WARN, why)
            return False
        if verdict == "drop":
            self.old(why)
            return False
        if verdict == "restart":
            self.health.event("status", DiagnosticStatus.WARN, why)
            self.restart()
        elif self.health.level("status") != DiagnosticStatus.OK:
            self.health.set("status", DiagnosticStatus.OK, "following the driver's statuses")
        return True


class ReadingWatch:
    """The ``readings`` condition: readings the sensor model cannot produce (guard.ReadingCheck),
    OK again once every agent warned about reads plausibly."""

    def __init__(self, check, health) -> None:
        """``check``: the agent's guard.ReadingCheck."""
        self.check = check
        self.health = health

    def take(self, idx: int, agent_id: str, value: float) -> None:
        """A reading ``value`` of agent ``agent_id`` (team index ``idx``) was taken."""
        warning = self.check.check(idx, agent_id, value)
        if warning:
            self.health.set("readings", DiagnosticStatus.WARN, warning)
        elif not self.check.warned and self.health.level("readings") != DiagnosticStatus.OK:
            self.health.set("readings", DiagnosticStatus.OK, f"the last {LOW_WINDOW} readings of every "
                            "agent warned about are plausible again")


class NoteLog:
    """The observer's notes (a restarted driver, a map with faint cells), each logged once, at
    level WARN on /diagnostics as in the log (condition ``team step``)."""

    def __init__(self, observer, health) -> None:
        self.observer = observer
        self.health = health
        self.noted: set[str] = set()

    def flush(self) -> None:
        notes, self.observer.notes[:] = list(self.observer.notes), []
        for note in notes:
            if note in self.noted:
                continue
            self.noted.add(note)
            self.health.event("team step", DiagnosticStatus.WARN, note)


class OldStatuses:
    """Statuses below the step answered (normal: a re-send that crossed the next step): logged at
    DEBUG, counted, and summed up in one INFO line at most every ``period_s`` seconds."""

    def __init__(self, logger, dropped_by: Counter, period_s: float, clock: Clock = time.monotonic) -> None:
        """``dropped_by``: the node's count of dropped messages by kind (this adds 'old status')."""
        self.logger = logger
        self.dropped_by = dropped_by
        self.period_s = period_s
        self.clock = clock
        self.count = 0  # since the last summary
        self.since = 0.0

    def drop(self, why: str) -> None:
        self.dropped_by["old status"] += 1
        self.count += 1
        self.logger.debug(f"dropped status: {why}")

    def sum_up(self) -> None:
        """Log the summary line when one is due."""
        now = self.clock()
        if self.count and now - self.since >= self.period_s:
            self.logger.info(
                f"{self.count} statuses below the step answered dropped in the last "
                f"{now - self.since:.0f} s (a driver's re-sends that crossed its next step: normal; "
                f"{self.dropped_by['old status']} in all)")
            self.count = 0
        if not self.count:
            self.since = now


class StallWatch:
    """The ``team step`` condition: a team step (or a round of poses and readings no status names)
    this agent has not been able to decide for ``timeout_s`` seconds, reported once with what it
    waits for; OK again when that step is decided."""

    def __init__(self, observer, health, timeout_s: float, has_policy: Callable[[], bool],
                 clock: Clock = time.monotonic) -> None:
        """``observer``: the agent's TeamObserver; ``has_policy``: whether a policy is running."""
        self.observer = observer
        self.health = health
        self.timeout_s = timeout_s
        self.has_policy = has_policy
        self.clock = clock
        #: Stall reports logged (one per stalled step), for tests and monitoring.
        self.reported = 0
        self._since: tuple[object, float] | None = None  # (what, since when)
        self._report: tuple[object, str] | None = None  # (what, report) once logged

    def check(self) -> None:
        o = self.observer
        what: object = o.clock.open_tick()
        if what is None:
            orphan = o.orphan_round()
            if orphan is not None:
                what = ("orphan", orphan)
        now = self.clock()
        if what is None:
            self._since = None
            return
        if self._since is None or self._since[0] != what:
            self._since = (what, now)
            return
        waited = now - self._since[1]
        if waited < self.timeout_s or (self._report and self._report[0] == what):
            return
        need, have, head = self._waiting(what)
        report = (f"stalled: {head} not decided after {waited:.1f} s; waiting for: {'; '.join(need) or '?'}; "
                  f"have: {'; '.join(have) or 'nothing else'}")
        self._report = (what, report)
        self.reported += 1
        self.health.set("team step", DiagnosticStatus.WARN, report, {
            "waiting_for": "; ".join(need), "have": "; ".join(have), "waited_s": f"{waited:.1f}"})

    def _waiting(self, what: object) -> tuple[list[str], list[str], str]:
        """(what the stalled ``what`` waits for, what is there, how the report names it)."""
        o = self.observer
        if isinstance(what, Tick):
            need, have = o.waiting_for()
            if not self.has_policy():
                need.append("a policy")
            return need, have, f"episode {what.episode} step {what.step} (stamp {show_stamp(what.stamp)})"
        c = o.clock
        have = [f"last status answered: episode {c.episode} step {c.step} stamped "
                f"{show_stamp(c.stamp)}" if c.step >= 0 else "no status answered yet"]
        return ([f"an EpisodeStatus with header.stamp {show_stamp(what[1])}"], have,
                f"poses and readings of every agent stamped {show_stamp(what[1])}")

    def over(self, tick) -> None:
        """``tick`` is decided."""
        if self._report is not None and self._report[0] == tick:
            self.health.set("team step", DiagnosticStatus.OK,
                            f"deciding again: episode {tick.episode} step {tick.step} decided")
            self._report = None
        self._since = None


class TeamWatch:
    """The ``team`` and ``agents`` conditions: teammates taken out when their pose or reading has not
    come for the lost watch's timeout while a step waits for it, taken back when heard again; and
    teammates that have stopped moving while their UAVs still report."""

    def __init__(self, agent_id: str, observer, lost_watch, estimate, health, logger,
                 decide: Callable[[], None], clock: Clock = time.monotonic) -> None:
        """``lost_watch``: the agent's guard.LostWatch; ``estimate``: its TeamEstimate (who moves,
        who publishes the estimate); ``decide``: decides the pending step if it can be now."""
        self.agent_id = agent_id
        self.observer = observer
        self.lost_watch = lost_watch
        self.estimate = estimate
        self.health = health
        self.logger = logger
        self.decide = decide
        self.clock = clock
        self._pending_since: tuple[Tick | None, float] = (None, 0.0)  # (tick, since when it waits)

    def check_lost(self) -> None:
        """Take out the teammates silent for too long while the step waits for them."""
        o = self.observer
        t = o.clock.open_tick()
        if t is None:
            return
        if self._pending_since[0] != t:
            self._pending_since = (t, self.clock())
        # Alive, if mis-stamped: something newer than the step answered, but not far ahead of the
        # step waited on (a pose stamped an hour ahead keeps nobody in the team).
        fresh = {j for j in range(o.num_agents)
                 if any(o.clock.stamp < o.rounds.latest.get((kind, j), -1) <= t.stamp + FUTURE_NS
                        for kind in ("pose", "reading"))}
        newly = self.lost_watch.check(o.missing(), self._pending_since[1], fresh)
        for idx, _why in newly:
            o.absent.add(idx)
        if newly:
            self._report_team()
            self.decide()

    def heard(self, kind: str, agent_id: str) -> None:
        """A ``kind`` ('pose', 'reading') of ``agent_id`` was taken."""
        o = self.observer
        idx = contract.agent_index(agent_id, o.num_agents)
        self.lost_watch.seen(kind, idx)
        if idx in o.absent:
            self.readmit()

    def readmit(self) -> None:
        """Take back into the team every teammate taken out whose pose and reading stamped with the
        step waited on are here (a pose or reading with any other stamp, one far in the future
        above all, brings nobody back)."""
        o = self.observer
        t = o.clock.open_tick()
        if t is None or not o.absent:
            return
        here = set(o.rounds.present(t.stamp))
        for idx in sorted(o.absent & here):
            o.absent.discard(idx)
            if self.lost_watch.back(idx):
                self.logger.info(f"{o.ids[idx]} is heard again: back in the team")
                self._report_team()

    def _report_team(self) -> None:
        o, lost = self.observer, self.lost_watch.lost
        if lost:
            text = "; ".join(f"{o.ids[j]} lost ({why})" for j, why in sorted(lost.items()))
            self.health.set("team", DiagnosticStatus.WARN,
                            f"{text}: deciding with the {o.num_agents - len(lost)} agents heard; taken back "
                            "when its pose and reading come again",
                            {"lost": ", ".join(o.ids[j] for j in sorted(lost))})
        else:
            self.health.set("team", DiagnosticStatus.OK, f"all {o.num_agents} agents heard")

    def report_silent(self, tick) -> None:
        """Report, once per change, the teammates that have stopped moving while their UAVs still
        report (the driver steps on without their moves: a dead or cut-off agent process); OK again
        when every teammate moves (a teammate whose UAV is lost too is the ``team`` condition's)."""
        o, role = self.observer, self.estimate.role
        silent = [j for j in self.estimate.silent(tick) if j not in o.absent]
        if not silent:
            if self.health.level("agents") != DiagnosticStatus.OK:
                self.health.set("agents", DiagnosticStatus.OK, f"every teammate of {self.agent_id} moves")
            return
        parts = []
        for j in silent:
            heard = role.last.get(j)
            last = "no move heard" if heard is None else \
                f"last move for episode {heard[0][0]} step {heard[0][1]}"
            parts.append(f"{o.ids[j]} ({last})")
        names = ", ".join(o.ids[j] for j in silent)
        takes = f"; {self.agent_id} publishes the team's source estimate" \
            if self.estimate.publishing and role.own > 0 else ""
        self.health.set("agents", DiagnosticStatus.WARN, (
            f"{', '.join(parts)}: no move while its UAV still reports; the driver steps on without it "
            f"(its agent process died or lost its link?){takes}"), {"silent": names})
