"""The simulator's start gate: the first step waits until DDS has matched every reader that must
hear the whole run, because a reliable, volatile message published before a reader is matched never
reaches it.

Three counts, each of readers or writers matched with the simulator's own endpoints:

* status listeners (``wait_for_subscribers``): the agents (or the in-process team's feed) and a
  recorder. The simulator's own watch of its status topic (medc_sim.watch) is matched at once and
  is not counted: it would otherwise stand in for a missing listener.
* move publishers: every agent's, whenever ``wait_for_subscribers`` > 0, so listeners that are
  recorders never start a team whose agents are not there.
* results readers (``wait_for_results_readers``): the launcher's monitor and a recorder. The
  results are latched only while the simulator lives; a finished simulator also waits for this
  many before it exits (medc_sim.sim_node). Without this count a recorder, matched first, let
  the simulator run its episodes and exit before the launcher's monitor was discovered: the
  launcher then waited for results that no longer existed (docs/ros-guide.md, "Record, watch, export").

After ``timeout_s`` the simulator starts anyway and logs what was missing.
"""

from __future__ import annotations

import time
from collections.abc import Callable

#: Seconds the first step waits for the readers and writers above before it starts anyway.
START_WAIT_S = 30.0
#: Status subscriptions the simulator holds itself (GraphWatch's): matched at once, never counted.
OWN_STATUS_READERS = 1


class StartGate:
    """Counts what a simulator's endpoints have matched (see the module docstring)."""

    def __init__(self, status_pub, move_subs: list, results_pub, listeners: int, results_readers: int,
                 timeout_s: float = START_WAIT_S, clock: Callable[[], float] = time.monotonic) -> None:
        """``status_pub``, ``move_subs`` (one per agent), ``results_pub``: the simulator's endpoints
        whose matches are counted; ``listeners`` and ``results_readers``: the counts waited for."""
        if listeners < 0 or results_readers < 0:
            raise ValueError(f"wait_for_subscribers and wait_for_results_readers must be >= 0, got "
                             f"{listeners} and {results_readers}")
        self.status_pub = status_pub
        self.move_subs = move_subs
        self.results_pub = results_pub
        self.listeners = listeners
        self.results_readers = results_readers
        self.clock = clock
        self.deadline = clock() + timeout_s

    def counts(self) -> tuple[int, int, int]:
        """(status listeners, agents' move publishers, results readers) matched now."""
        listeners = max(0, self.status_pub.get_subscription_count() - OWN_STATUS_READERS)
        movers = sum(1 for sub in self.move_subs if sub.get_publisher_count() > 0)
        return listeners, movers, self.results_pub.get_subscription_count()

    def missing(self) -> list[str]:
        """What the first step still waits for, in words (empty: ready)."""
        listeners, movers, readers = self.counts()
        agents = len(self.move_subs) if self.listeners > 0 else 0
        out = []
        if listeners < self.listeners:
            out.append(f"{listeners} of {self.listeners} expected status subscribers")
        if movers < agents:
            out.append(f"{movers} of {agents} agents' move publishers")
        if readers < self.results_readers:
            out.append(f"{readers} of {self.results_readers} expected episode-result readers")
        return out

    def expired(self) -> bool:
        return self.clock() > self.deadline
