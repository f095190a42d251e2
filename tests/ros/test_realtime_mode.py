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


@pytest.mark.ros
def test_realtime_mode_keeps_the_rate_and_a_silent_agent_stays(graph, bundles):
    # Own subscriptions per agent, so that taking agent_2 off the executor silences it entirely.
    executor, sim, agents = graph(bundles["a"], 0, shared_feed=False, **SCENARIO)
    silent = agents[2]
    executor.remove_node(silent)  # agent_2 crashed: no moves from it any more
    assert spin_until(executor, lambda: len(sim.core.trace) >= 3, 30)
    start, n0 = time.monotonic(), len(sim.core.trace)
    seen: dict[int, set] = {}  # episode -> cells agent_2 was seen on

    def watch() -> bool:
        seen.setdefault(sim.core.episode, set()).add(sim.core.positions()[2])
        return len(sim.core.trace) >= n0 + 20

    assert spin_until(executor, watch, 30)
    elapsed = time.monotonic() - start
    assert elapsed >= 19 / SCENARIO["rate_hz"]  # the timer, not the agents, sets the pace
    assert all(actions[2] is None for _, _, actions in sim.core.trace[n0:])
    assert all(len(cells) == 1 for cells in seen.values())  # within an episode it never moved
    assert any(actions[0] is not None for _, _, actions in sim.core.trace[n0:])
