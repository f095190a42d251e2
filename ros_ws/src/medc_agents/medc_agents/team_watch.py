"""The agent node's watch over its team: stalls, lost teammates, duplicate ids, a second driver.

A mixin of :class:`medc_agents.node.AgentNode` (it uses the node's observer, guards, health and
slot); the rules themselves live in :mod:`medc_agents.guard` and the team-state units
(:mod:`medc_agents.team_state`) and are tested without a node.
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticStatus
from medc_common import contract
from medc_interfaces.msg import AgentMove
from medc_training.untrusted import printable

from medc_agents.team_episode import Tick
from medc_agents.team_messages import show_stamp

#: Seconds without a repeat after which a fault that came from outside (another process moving as
#: this agent) is over: its condition is OK again.
CLEAR_S = 10.0
#: A pose or reading stamped more than this (ns) ahead of the step waited on is not a sign of life.
FUTURE_NS = 5_000_000_000


class TeamWatch:
    """Stall reports, lost and returning teammates, and the heartbeat's summary of an agent node."""

    _claimed_at: float | None = None  # when another process last moved as this agent

    def _on_own_move(self, msg: AgentMove) -> None:
        if msg.sender == self.sender:
            return
        self._claimed_at = time.monotonic()
        self.health.set("moves", DiagnosticStatus.WARN, (
            f"another process publishes moves as {self.agent_id} (sender {printable(str(msg.sender), 40)!r}; "
            f"this node is {self.sender}): two processes claim {self.agent_id}; stop one of them"))

    def _summary(self) -> dict[str, str]:
        o = self.observer
        return {"namespace": self.namespace_, "sender": self.sender, "session": self.gate.session or "",
                "episode": str(o.clock.episode), "step": str(o.clock.step), "decisions": str(self.decisions),
                "dropped": str(self.dropped), "old_statuses": str(self.dropped_by["old status"]),
                "absent": ", ".join(o.ids[j] for j in sorted(o.absent)) or "none",
                "policy": self.slot.current.description if self.slot.current is not None else "none",
                "estimate": ("publishing" if self.estimate.publishing else "standby") if self.estimate.enabled
                else "off"}

    def _flush_notes(self) -> None:
        """Log each new note of the observer once (a restarted driver, a map with faint cells), at
        level WARN on /diagnostics as in the log."""
        notes, self.observer.notes[:] = list(self.observer.notes), []
        for note in notes:
            if note in self._noted:
                continue
            self._noted.add(note)
            self.health.event("team step", DiagnosticStatus.WARN, note)

    def _watch(self) -> None:
        """Take silent teammates out; report, once, a team step this agent has not been able to
        decide for stall_timeout_s."""
        self._flush_notes()
        self._check_lost()
        self._sum_old_statuses()
        self.map_faults.check_due()
        if self._claimed_at is not None and time.monotonic() - self._claimed_at >= CLEAR_S:
            self._claimed_at = None
            self.health.set("moves", DiagnosticStatus.OK, f"no other process has moved as {self.agent_id} "
                            f"for {CLEAR_S:g} s")
        foreign = self.gate.foreign_now()
        if foreign:
            topic = contract.status_topic(self.namespace_)
            self.health.set("driver", DiagnosticStatus.WARN, (
                f"statuses from {len(foreign) + 1} driver sessions on {topic} (following "
                f"{self.gate.session or '(none)'!r}, held: {', '.join(foreign)}): a second graph shares this "
                "ROS_DOMAIN_ID and namespace; give each graph its own ROS_DOMAIN_ID or namespace"))
        elif self.health.level("driver") != DiagnosticStatus.OK:
            self.health.set("driver", DiagnosticStatus.OK, "one driver session")
        o = self.observer
        what: object = o.clock.open_tick()
        if what is None:
            orphan = o.orphan_round()
            if orphan is not None:
                what = ("orphan", orphan)
        now = time.monotonic()
        if what is None:
            self._stall_since = None
            return
        if self._stall_since is None or self._stall_since[0] != what:
            self._stall_since = (what, now)
            return
        waited = now - self._stall_since[1]
        if waited < self.stall_timeout_s or (self._stall_report and self._stall_report[0] == what):
            return
        if isinstance(what, Tick):
            need, have = o.waiting_for()
            head = f"episode {what.episode} step {what.step} (stamp {show_stamp(what.stamp)})"
            if self.slot.current is None:
                need.append("a policy")
        else:
            head = f"poses and readings of every agent stamped {show_stamp(what[1])}"
            need = [f"an EpisodeStatus with header.stamp {show_stamp(what[1])}"]
            c = o.clock
            have = [f"last status answered: episode {c.episode} step {c.step} stamped "
                    f"{show_stamp(c.stamp)}" if c.step >= 0 else "no status answered yet"]
        report = (f"stalled: {head} not decided after {waited:.1f} s; waiting for: {'; '.join(need) or '?'}; "
                  f"have: {'; '.join(have) or 'nothing else'}")
        self._stall_report = (what, report)
        self.stalls_reported += 1
        self.health.set("team step", DiagnosticStatus.WARN, report, {
            "waiting_for": "; ".join(need), "have": "; ".join(have), "waited_s": f"{waited:.1f}"})

    def _check_lost(self) -> None:
        o = self.observer
        t = o.clock.open_tick()
        if t is None:
            return
        if self._pending_since[0] != t:
            self._pending_since = (t, time.monotonic())
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
            self._maybe_decide()

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

    def _report_silent(self, tick) -> None:
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

    def _heard(self, kind: str, agent_id: str) -> None:
        o = self.observer
        idx = contract.agent_index(agent_id, o.num_agents)
        self.lost_watch.seen(kind, idx)
        if idx in o.absent:
            self._readmit()

    def _readmit(self) -> None:
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
                self.get_logger().info(f"{o.ids[idx]} is heard again: back in the team")
                self._report_team()

    def _stall_over(self, tick) -> None:
        if self._stall_report is not None and self._stall_report[0] == tick:
            message = f"deciding again: episode {tick.episode} step {tick.step} decided"
            self.health.set("team step", DiagnosticStatus.OK, message)
        self._stall_report = None if self._stall_report is None or self._stall_report[0] == tick \
            else self._stall_report
        self._stall_since = None
