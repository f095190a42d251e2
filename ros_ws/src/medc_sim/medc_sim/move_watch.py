"""The simulator's watch over the team's moves: the ``moves`` faults of any mode and, in stepped
mode, re-sent steps, stall reports, agents taken out after move_timeout_s and taken back when they
move again.

:class:`MoveFaults` and :class:`StepWatch` are owned by :class:`medc_sim.simulator.SimNode`, each built
from what it reads and reports to (the move book, a Health, a logger, callables that re-send or
advance the step, a clock) and tested without a node; the bookkeeping rules are
:class:`medc_sim.moves.MoveBook`'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus

from medc_sim.moves import ConflictingMove, DuplicateAgent, MoveRejected

#: An agent that has never moved is taken out only after this many times move_timeout_s.
STARTUP_FACTOR = 5.0
#: Seconds: a move fault (duplicate agent id, conflicting moves) of one kind is logged once per this
#: period, its repeats meanwhile summed up in one line; with no fault for this long, ``moves`` is OK.
FAULT_REPEAT_S = 10.0

Clock = Callable[[], float]


class MoveFaults:
    """The ``moves`` condition of a simulator: duplicate agent ids, conflicting and foreign moves."""

    def __init__(self, health, logger, create_timer: Callable[[float, Callable[[], None]], Any],
                 clock: Clock = time.monotonic, repeat_s: float | None = None) -> None:
        """``create_timer``: the node's (a 1 s timer is made at the first fault); ``repeat_s``: the
        period of :data:`FAULT_REPEAT_S` (its value when None)."""
        self.health = health
        self.logger = logger
        self.create_timer = create_timer
        self.clock = clock
        self.repeat_s = FAULT_REPEAT_S if repeat_s is None else repeat_s
        #: Per fault kind (e.g. 'conflict agent_1'): [when it was last logged, repeats since then].
        self.faults: dict[str, list] | None = None
        self._last = 0.0

    def report(self, kind: str, message: str, log: bool = True) -> None:
        """Report a move fault: WARN on /diagnostics (part ``moves``) with the latest message, logged
        (``log``) once per kind every ``repeat_s``; repeats meanwhile are counted and summed up in
        one line."""
        if self.faults is None:
            self.faults = {}
            self.create_timer(1.0, self.tick)
        now = self.clock()
        self._last = now
        seen = self.faults.get(kind)
        if seen is None or now - seen[0] >= self.repeat_s:
            self.faults[kind] = [now, 0]
            self.health.set("moves", DiagnosticStatus.WARN, message, log=log)
        else:
            seen[1] += 1
            self.health.set("moves", DiagnosticStatus.WARN, message, log=False)

    def refused(self, agent_id: str, exc: MoveRejected) -> bool:
        """Report a move of ``agent_id`` the move book refused; whether it counts as dropped (a
        conflicting move does not: it is a move of the team's, the first one taken)."""
        if isinstance(exc, DuplicateAgent):
            self.report(f"duplicate {agent_id}", f"duplicate agent id: {exc}")
            return True
        if isinstance(exc, ConflictingMove):
            self.report(f"conflict {agent_id}", f"conflicting moves: {exc}")
            return False
        self.logger.warning(f"dropped move: {exc}")
        if "another graph" in str(exc):
            self.report(f"foreign {agent_id}", f"foreign move: {exc}", log=False)
        return True

    def tick(self) -> None:
        """Sum up the repeats of each kind whose period is over; OK after ``repeat_s`` without one."""
        now = self.clock()
        for kind, seen in list(self.faults.items()):
            if now - seen[0] >= self.repeat_s:
                if seen[1] and not kind.startswith("foreign"):
                    self.logger.warning(f"{kind}: {seen[1]} more in the last {now - seen[0]:.0f} s "
                                        "(logged once per period; the latest on /diagnostics)")
                del self.faults[kind]
        if self._last and now - self._last >= self.repeat_s:
            self._last = 0.0
            if self.health.level("moves") != DiagnosticStatus.OK:
                self.health.set("moves", DiagnosticStatus.OK, f"no duplicate or conflicting move for "
                                f"{self.repeat_s:g} s")


class StepWatch:
    """The timing of the step in play and, in stepped mode, its watch: the ``team step`` condition
    (moves missing for stall_timeout_s), re-sends every resend_s, and the ``team`` condition (agents
    taken out after move_timeout_s, taken back when they move again)."""

    def __init__(self, book, ids: list[str], health, logger, *, send: Callable[[], None],
                 advance: Callable[[], None], running: Callable[[], bool], resend_s: float,
                 stall_timeout_s: float, move_timeout_s: float, rate_hz: float,
                 clock: Clock = time.monotonic, perf: Clock = time.perf_counter) -> None:
        """``book``: the simulator's MoveBook; ``send``: re-publishes the step in play; ``advance``:
        steps on with the moves in the book; ``running``: whether the simulator has started and not
        finished; ``clock``: when a step was last sent; ``perf``: the step's latency clock."""
        self.book = book
        self.ids = ids
        self.health = health
        self.logger = logger
        self.send = send
        self.advance = advance
        self.running = running
        self.resend_s = resend_s
        self.stall_timeout_s = stall_timeout_s
        self.move_timeout_s = move_timeout_s
        self.rate_hz = rate_hz
        self.clock = clock
        self.perf = perf
        #: Steps re-published for moves missing.
        self.resends = 0
        self.sent_at = 0.0
        self.opened_at: float | None = None  # the step in play's publication, until its last move
        self.first_move_at: float | None = None  # when the step's first move came
        self.stall_logged: tuple[int, int] | None = None

    def opened(self) -> None:
        """A new step is published."""
        if self.stall_logged is not None and self.health.level("team step") != DiagnosticStatus.OK:
            self.health.set("team step", DiagnosticStatus.OK, "stepping again")
        self.opened_at = self.perf()
        self.first_move_at = None

    def sent(self) -> None:
        """The step in play was published (first or again)."""
        self.sent_at = self.clock()

    def took(self) -> None:
        """A new move of the step in play was taken."""
        if self.first_move_at is None:
            self.first_move_at = self.perf()

    def latency(self) -> float | None:
        """Seconds from publishing the step to its last move, once it is complete (None after)."""
        if self.opened_at is None:
            return None
        latency, self.opened_at = self.perf() - self.opened_at, None
        return latency

    def resend_tick(self) -> None:
        """Re-publish a step whose moves are missing for resend_s; report it once after
        stall_timeout_s."""
        if not self.running() or self.clock() - self.sent_at < self.resend_s:
            return
        self.resends += 1
        waited = self.perf() - self.opened_at if self.opened_at is not None else 0.0
        step = (self.book.episode, self.book.step)
        if 0 < self.stall_timeout_s <= waited and self.stall_logged != step and not self.book.complete:
            self.stall_logged = step
            missing = ", ".join(self.ids[i] for i in self.book.missing)
            self.health.set("team step", DiagnosticStatus.WARN, (
                f"episode {step[0]} step {step[1]}: no move from {missing} after {waited:.1f} s; "
                f"re-sending the step every {self.resend_s:g} s (the agents' logs and /diagnostics "
                "say what they wait for)"), {"missing": missing, "waited_s": f"{waited:.1f}"})
        self.send()

    def report_returned(self) -> None:
        """Log the agents taken out that moved again, and report the team."""
        for idx in self.book.returned:
            self.logger.info(f"{self.ids[idx]} moved again: back in the team")
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

    def move_timeout_tick(self) -> None:
        """Stepped mode: agents with no move move_timeout_s after the step's first move are taken
        out, and the step goes on (a team with no answer at all is a stall, re-sent and reported,
        not stepped)."""
        first = self.first_move_at
        if not self.running() or first is None or self.book.complete:
            return
        waited = self.perf() - first
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
            self.opened_at = None
            self.advance()
