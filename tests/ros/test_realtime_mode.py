"""Realtime mode steps at a fixed rate; an agent whose move is missing stays where it is."""

from __future__ import annotations

import time

import pytest
from ros_helpers import spin_until

SCENARIO = {
    "agents": 3,
    "walls": 1,
    "grid": 10,
    "max_steps": 200,
    "seed": 6,
    "mode": "realtime",
    "rate_hz": 20.0,
}


@pytest.mark.timing
@pytest.mark.ros
def test_realtime_mode_keeps_the_rate_and_a_silent_agent_stays(graph, bundles):
    # Own subscriptions per agent, so that taking agent_2 off the executor silences it entirely.
    executor, sim, agents = graph(bundles["a"], 0, shared_feed=False, **SCENARIO)
    silent = agents[2]
    executor.remove_node(silent)  # agent_2 crashed: no moves from it any more
    assert spin_until(executor, lambda: len(sim.core.trace) >= 3, 60)
    start, n0 = time.monotonic(), len(sim.core.trace)
    seen: dict[int, set] = {}  # episode -> cells agent_2 was seen on

    def watch() -> bool:
        """20 steps, and a move of agent_0 among them (on a loaded machine its move may miss a
        step's 50 ms: then the step goes without it)."""
        seen.setdefault(sim.core.episode, set()).add(sim.core.positions()[2])
        steps = sim.core.trace[n0:]
        return len(steps) >= 20 and any(actions[0] is not None for _, _, actions in steps)

    assert spin_until(executor, watch, 120)
    steps = sim.core.trace[n0:]
    elapsed = time.monotonic() - start
    # The timer, not the agents, sets the pace: n steps take at least n - 2 periods (a late tick
    # is not repeated to catch up, but the tick after it comes on time, however soon after).
    assert elapsed >= (len(steps) - 2) / SCENARIO["rate_hz"], (elapsed, len(steps))
    assert all(actions[2] is None for _, _, actions in steps)
    assert all(len(cells) == 1 for cells in seen.values())  # within an episode it never moved
