"""Bad input on any topic is logged and dropped; every node keeps running and the episodes are
exactly the ones the graph plays without it."""

from __future__ import annotations

import math

import pytest
import torch
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from medc_common import contract
from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading
from medc_sim import messages
from nav_msgs.msg import OccupancyGrid
from ros_helpers import reference_episodes, spin_until
from std_msgs.msg import String

SCENARIO = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 4}
EPISODES = 4


@pytest.mark.timing
@pytest.mark.ros
def test_bad_messages_on_every_topic_are_dropped(graph, bundles, tmp_path):
    import rclpy

    lengths, _, trace = reference_episodes(bundles["a"], EPISODES, **SCENARIO)
    executor, sim, agents = graph(bundles["a"], EPISODES, **SCENARIO)
    attacker = rclpy.create_node("attacker")
    executor.add_node(attacker)
    ns = contract.DEFAULT_NAMESPACE
    pub = {
        "move": attacker.create_publisher(
            AgentMove, contract.move_topic(ns, "agent_0"), contract.RELIABLE_QOS
        ),
        "pose": attacker.create_publisher(
            PoseStamped, contract.pose_topic(ns, "agent_1"), contract.SENSOR_QOS
        ),
        "radiation": attacker.create_publisher(
            RadiationReading, contract.radiation_topic(ns, "agent_2"), contract.SENSOR_QOS
        ),
        "map": attacker.create_publisher(OccupancyGrid, contract.map_topic(ns), contract.LATCHED_QOS),
        "status": attacker.create_publisher(EpisodeStatus, contract.status_topic(ns), contract.RELIABLE_QOS),
        "policy": attacker.create_publisher(
            String, contract.policy_topic(ns, "agent_1"), contract.LATCHED_QOS
        ),
    }
    garbage = tmp_path / "not_a_bundle.safetensors"
    garbage.write_bytes(b"PK\x03\x04 definitely not safetensors")
    stamp = Time(sec=1)

    def bad_messages():
        yield "move", AgentMove(agent_id="agent_9", episode=sim.core.episode, step=sim.core.step, action=1)
        yield (
            "move",
            AgentMove(agent_id="agent_0", episode=sim.core.episode + 7, step=0, action=1),
        )  # dead episode
        yield "move", AgentMove(agent_id="agent_0", episode=max(sim.core.episode - 1, 0), step=99, action=2)
        yield "move", AgentMove(agent_id="agent_0", episode=sim.core.episode, step=sim.core.step, action=200)
        nan_pose = messages.pose_msg((1, 1), stamp, contract.GridGeometry(10, 10))
        nan_pose.pose.position.y = math.nan
        yield "pose", nan_pose
        yield "pose", messages.pose_msg((50, 1), stamp, contract.GridGeometry(10, 10))  # off the grid
        yield "radiation", messages.reading_msg("agent_2", math.inf, 0.0, stamp)
        yield "radiation", messages.reading_msg("agent_0", 3.0, 0.0, stamp)  # names another agent
        short = messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), stamp, 1.0)
        short.data = short.data[:37]
        yield "map", short
        yield "status", messages.status_msg(["agent_0", "ghost"], 0, 0, stamp, stamp)
        yield "policy", String(data="/no/such/bundle.safetensors")
        yield "policy", String(data=str(garbage))

    # Let the graph play its first steps, then inject the whole set of bad messages every few steps.
    assert spin_until(executor, lambda: len(sim.core.trace) >= 3, 30)
    injected = 0
    while not sim.finished and injected < 5:
        for topic, msg in bad_messages():
            pub[topic].publish(msg)
        injected += 1
        target = len(sim.core.trace) + 5
        assert spin_until(executor, lambda t=target: len(sim.core.trace) >= t or sim.finished, 30)
    assert spin_until(executor, lambda: sim.finished, 120)
    attacker.destroy_node()

    assert [r.length for r in sim.core.results] == lengths
    assert sim.core.trace == trace
    # Reliable topics: every bad message is counted. Sensor data is best effort: at least one per kind.
    assert sim.dropped == 4 * injected  # four bad moves per round
    for agent in agents:
        # The simulator re-publishes its own map when another one comes (the map topic keeps one
        # message), so a bad map may be superseded before an agent reads it: at least one per agent.
        assert 1 <= agent.dropped_by["map"] <= injected and agent.dropped_by["status"] == injected
        assert agent.dropped_by["pose"] >= 1 and agent.dropped_by["radiation"] >= 1
    assert agents[1].dropped_by["policy"] >= injected  # latched topic, depth 1: the last one of a burst
    assert agents[1].slot.current.source == str(bundles["a"])  # bad policies refused, old one runs
    # The foreign map and the status of another session are reported by the simulator.
    assert sim.health.level("map") == sim.health.level("graph") == DiagnosticStatus.WARN
    assert sim.watch.foreign_maps >= 1 and "" in sim.watch.foreign_sessions
