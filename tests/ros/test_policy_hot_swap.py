"""Policies are swapped at runtime, by parameter or topic; invalid bundles are refused."""

from __future__ import annotations

import pytest
from medc_common import contract
from rclpy.parameter import Parameter
from ros_helpers import replay_masks, spin_until
from std_msgs.msg import String

SCENARIO = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 2}


@pytest.mark.timing
@pytest.mark.ros
def test_swap_by_parameter_service_and_by_topic(graph, bundles, tmp_path):
    import rclpy
    from rclpy.parameter_client import AsyncParameterClient

    executor, sim, agents = graph(bundles["a"], 0, **SCENARIO)
    operator = rclpy.create_node("operator")
    executor.add_node(operator)
    assert spin_until(executor, lambda: len(sim.core.trace) >= 10, 60)

    # 1. The parameter service of agent_0, as `ros2 param set` would call it.
    client = AsyncParameterClient(operator, "/medc/medc_agent_0")
    assert spin_until(executor, lambda: client.services_are_ready(), 60)

    def set_policy(path: str):
        future = client.set_parameters([Parameter("policy", value=path)])
        assert spin_until(executor, future.done, 60)
        return future.result().results[0]

    result = set_policy(str(bundles["north"]))
    assert result.successful, result.reason
    swapped_at = len(sim.core.trace)
    assert spin_until(executor, lambda: len(sim.core.trace) >= swapped_at + 25, 60)
    # From the step after the swap on, agent_0 moves N whenever N is allowed ('north' bundle).
    trace = list(sim.core.trace)
    masks = replay_masks(trace, **SCENARIO)
    north_allowed = [i for i in range(swapped_at + 1, len(trace)) if masks[i][0, 0]]
    assert len(north_allowed) >= 5
    assert all(trace[i][2][0] == 0 for i in north_allowed)
    assert not all(trace[i][2][0] == 0 for i in range(swapped_at - 1) if masks[i][0, 0])

    # 2. A bundle for another grid size is refused with the reason; 'north' keeps running.
    result = set_policy(str(bundles["grid30"]))
    assert not result.successful and "shape" in result.reason
    garbage = tmp_path / "x.safetensors"
    garbage.write_text("{}")
    assert not set_policy(str(garbage)).successful
    assert agents[0].slot.current.source == str(bundles["north"])

    # 3. The team policy topic swaps every agent at once.
    pub = operator.create_publisher(
        String, contract.team_policy_topic(contract.DEFAULT_NAMESPACE), contract.LATCHED_QOS
    )
    pub.publish(String(data=str(bundles["b"])))
    assert spin_until(executor, lambda: all(a.slot.current.source == str(bundles["b"]) for a in agents), 60)
    # The graph keeps playing after the swaps.
    n = len(sim.core.trace)
    assert spin_until(executor, lambda: len(sim.core.trace) >= n + 10, 60)
    assert sim.dropped == 0
