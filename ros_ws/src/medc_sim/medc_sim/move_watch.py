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


class MoveWatch:
    """Stepped-mode move watching of a simulator node."""

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
