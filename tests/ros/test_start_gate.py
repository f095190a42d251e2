"""The simulator's start gate (medc_sim.start_gate): its own status watch is no listener, the first
step waits for the episode-result readers it is told of (the launcher's monitor, a recorder), and
a finished simulator waits for them too before it exits, so a recorder matched first cannot let
the run end before the launcher hears it."""

from __future__ import annotations

import time

import pytest
from ros_helpers import spin_until


def _sim(ns: str, **params):
    from medc_sim.simulator import SimNode
    from rclpy.parameter import Parameter

    base = {"namespace": ns, "agents": 1, "grid": 8, "walls": 0, "max_steps": 5}
    return SimNode(parameter_overrides=[Parameter(k, value=v) for k, v in (base | params).items()])


@pytest.mark.timing
@pytest.mark.ros
def test_the_simulators_own_status_watch_is_not_a_listener(rclpy_context):
    """One agent's move publisher and no status subscriber but the simulator's own watch: the
    gate (wait_for_subscribers 1) stays shut until a real listener comes."""
    import rclpy
    from medc_interfaces.msg import AgentMove, EpisodeStatus
    from rclpy.executors import SingleThreadedExecutor

    ns = "/gate_own"
    sim = _sim(ns, wait_for_subscribers=1)
    other = rclpy.create_node("gate_agent")
    executor = SingleThreadedExecutor()
    executor.add_node(sim)
    executor.add_node(other)
    try:
        other.create_publisher(AgentMove, f"{ns}/agent_0/move", 10)
        assert spin_until(executor, lambda: sim.move_subs[0].get_publisher_count() == 1, 60.0)
        assert sim.status_pub.get_subscription_count() == 1  # the watch, matched at once
        spin_until(executor, lambda: sim.started, 1.0)
        assert not sim.started, "the simulator's own status subscription opened its start gate"
        assert sim.gate.missing() == ["0 of 1 expected status subscribers"]
        other.create_subscription(EpisodeStatus, f"{ns}/episode", lambda m: None, 10)
        assert spin_until(executor, lambda: sim.started, 60.0)
    finally:
        executor.shutdown()
        sim.destroy_node()
        other.destroy_node()
    with pytest.raises(ValueError, match="wait_for_subscribers and wait_for_results_readers must be >= 0"):
        _sim(ns, wait_for_results_readers=-1)


@pytest.mark.timing
@pytest.mark.ros
def test_the_first_step_waits_for_every_results_reader(rclpy_context):
    import rclpy
    from medc_common import contract
    from medc_interfaces.msg import EpisodeStatus
    from rclpy.executors import SingleThreadedExecutor

    ns = "/gate_results"
    sim = _sim(ns, wait_for_subscribers=0, wait_for_results_readers=2)
    readers = rclpy.create_node("gate_readers")
    executor = SingleThreadedExecutor()
    executor.add_node(sim)
    executor.add_node(readers)
    try:
        readers.create_subscription(EpisodeStatus, f"{ns}/episode_result", lambda m: None,
                                    contract.RESULTS_QOS)
        assert spin_until(executor, lambda: sim.results_pub.get_subscription_count() == 1, 60.0)
        spin_until(executor, lambda: sim.started, 1.0)
        assert not sim.started, "one results reader of two started the simulator"
        assert sim.gate.missing() == ["1 of 2 expected episode-result readers"]
        readers.create_subscription(EpisodeStatus, f"{ns}/episode_result", lambda m: None,
                                    contract.RESULTS_QOS)
        assert spin_until(executor, lambda: sim.started, 60.0)
        assert sim.gate.missing() == []
    finally:
        executor.shutdown()
        sim.destroy_node()
        readers.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_a_finished_simulator_waits_for_its_results_readers(rclpy_context, monkeypatch):
    """medc-sim's last phase (sim_node.spin_episodes): with one of its two results readers it waits
    the whole RESULTS_READER_WAIT_S before lingering; with both, only the linger (1 s), ending
    long before that wait would."""
    import rclpy
    from medc_common import contract
    from medc_interfaces.msg import EpisodeStatus
    from medc_sim import sim_node
    from rclpy.executors import SingleThreadedExecutor

    wait_s = 5.0
    monkeypatch.setattr(sim_node, "RESULTS_READER_WAIT_S", wait_s)
    ns = "/gate_end"
    sim = _sim(ns, wait_for_subscribers=0, wait_for_results_readers=2)
    readers = rclpy.create_node("end_readers")
    executor = SingleThreadedExecutor()
    executor.add_node(sim)
    executor.add_node(readers)
    try:
        readers.create_subscription(EpisodeStatus, f"{ns}/episode_result", lambda m: None,
                                    contract.RESULTS_QOS)
        assert spin_until(executor, lambda: sim.results_pub.get_subscription_count() == 1, 60.0)
        sim.finished = True
        start = time.monotonic()
        sim_node.spin_episodes(sim, executor)
        one = time.monotonic() - start
        readers.create_subscription(EpisodeStatus, f"{ns}/episode_result", lambda m: None,
                                    contract.RESULTS_QOS)
        assert spin_until(executor, lambda: sim.results_pub.get_subscription_count() == 2, 60.0)
        start = time.monotonic()
        sim_node.spin_episodes(sim, executor)
        both = time.monotonic() - start
    finally:
        executor.shutdown()
        sim.destroy_node()
        readers.destroy_node()
    assert one >= wait_s + 0.9, one  # waiting for the second reader, then the 1 s linger
    assert 0.9 <= both < wait_s, both
