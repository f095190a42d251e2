"""The simulator's watch over the team's moves in stepped mode: re-sent steps, stall reports, agents
taken out after move_timeout_s and taken back when they move again.

A mixin of :class:`medc_sim.node.SimNode` (it uses the node's move book, health and timing fields);
the bookkeeping rules are :class:`medc_sim.moves.MoveBook`'s, tested without a node.
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticStatus

#: An agent that has never moved is taken out only after this many times move_timeout_s.
STARTUP_FACTOR = 5.0
#: Seconds: a move fault (duplicate agent id, conflicting moves) of one kind is logged once per this
#: period, its repeats meanwhile summed up in one line; with no fault for this long, ``moves`` is OK.
FAULT_REPEAT_S = 10.0


class MoveWatch:
    """Stepped-mode move watching of a simulator node, and the ``moves`` faults of any mode."""

    #: Per fault kind (e.g. 'conflict agent_1'): [when it was last logged, repeats since then].
    _faults: dict[str, list] | None = None
    _last_fault = 0.0

    def _move_fault(self, kind: str, message: str, log: bool = True) -> None:
        """Report a move fault: WARN on /diagnostics (part ``moves``) with the latest message, logged
        (``log``) once per kind every FAULT_REPEAT_S; repeats meanwhile are counted and summed up in
        one line."""
        if self._faults is None:
            self._faults = {}
            self.create_timer(1.0, self._faults_tick)
        now = time.monotonic()
        self._last_fault = now
        seen = self._faults.get(kind)
        if seen is None or now - seen[0] >= FAULT_REPEAT_S:
            self._faults[kind] = [now, 0]
            self.health.set("moves", DiagnosticStatus.WARN, message, log=log)
        else:
            seen[1] += 1
            self.health.set("moves", DiagnosticStatus.WARN, message, log=False)

    def _faults_tick(self) -> None:
        now = time.monotonic()
        for kind, seen in list(self._faults.items()):
            if now - seen[0] >= FAULT_REPEAT_S:
                if seen[1] and not kind.startswith("foreign"):
                    self.get_logger().warning(f"{kind}: {seen[1]} more in the last {now - seen[0]:.0f} s "
                                              "(logged once per period; the latest on /diagnostics)")
                del self._faults[kind]
        if self._last_fault and now - self._last_fault >= FAULT_REPEAT_S:
            self._last_fault = 0.0
            if self.health.level("moves") != DiagnosticStatus.OK:
                self.health.set("moves", DiagnosticStatus.OK, f"no duplicate or conflicting move for "
                                f"{FAULT_REPEAT_S:g} s")

    def _resend_tick(self) -> None:
        if self.started and not self.finished and time.monotonic() - self._published_at >= self.resend_s:
            self.resends += 1
            waited = time.perf_counter() - self._step_t0 if self._step_t0 is not None else 0.0
            step = (self.book.episode, self.book.step)
            if 0 < self.stall_timeout_s <= waited and self._stall_logged != step and not self.book.complete:
                self._stall_logged = step
                missing = ", ".join(self.ids[i] for i in self.book.missing)
                self.health.set("team step", DiagnosticStatus.WARN, (
                    f"episode {step[0]} step {step[1]}: no move from {missing} after {waited:.1f} s; "
                    f"re-sending the step every {self.resend_s:g} s (the agents' logs and /diagnostics "
                    "say what they wait for)"), {"missing": missing, "waited_s": f"{waited:.1f}"})
            self._send_state()

    def _report_returned(self) -> None:
        for idx in self.book.returned:
            self.get_logger().info(f"{self.ids[idx]} moved again: back in the team")
        if self.book.returned:
            self.book.returned.clear()
            self._report_lost()

    def _report_lost(self) -> None:
        lost = sorted(self.book.lost)
        if lost:
            names = ", ".join(self.ids[i] for i in lost)
            self.health.set("team", DiagnosticStatus.WARN, (
                f"{names} lost: no move within move_timeout_s ({self.move_timeout_s:g} s); staying in place, "
                "the team steps without waiting for it until it moves again"), {"lost": names})
        else:
            self.health.set("team", DiagnosticStatus.OK, f"all {len(self.ids)} agents moving")

    def _move_timeout_tick(self) -> None:
        """Stepped mode: agents with no move move_timeout_s after the step's first move are taken
        out, and the step goes on (a team with no answer at all is a stall, re-sent and reported,
        not stepped)."""
        first = self._first_move_at
        if not self.started or self.finished or first is None or self.book.complete:
            return
        waited = time.perf_counter() - first
        if waited < self.move_timeout_s:
            return
        # An agent that has never moved may still be starting: it is given STARTUP_FACTOR times as long.
        newly = [i for i in self.book.missing if i not in self.book.lost
                 and (self.book.known[i] or waited >= STARTUP_FACTOR * self.move_timeout_s)]
        if not newly:
            return
        self.book.take_out(newly)
        self._report_lost()
        if self.book.complete and self.rate_hz <= 0:
            self._step_t0 = None
            self._advance()
