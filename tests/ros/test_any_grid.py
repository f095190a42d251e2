"""Any area size the observation allows: an agent whose observation does not depend on the grid (an
agent-centred window) takes the map it is given; one whose observation shows the whole grid
('maps') refuses other sizes, saying why. The shipped team plays a 17x17 map in the ROS graph."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from ros_helpers import spin_until

TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"


def grid_msg(size: int, walls=None):
    from builtin_interfaces.msg import Time
    from medc_sim import messages

    walls = torch.zeros(size, size, dtype=torch.bool) if walls is None else walls
    return messages.grid_msg(walls, Time(sec=1), 1.0)


@pytest.mark.parametrize("observation", ["ego6+estimate", "ego3"])
def test_an_agent_centred_observer_takes_any_square_map(observation):
    from medc_agents.team_state import TeamObserver

    obs = TeamObserver("agent_0", 3, 13, observation=observation)
    obs.add_map(grid_msg(17))  # not 13x13: taken
    assert obs.any_grid and obs.map_geometry(1_000_000_000).height == 17
    with pytest.raises(ValueError, match="square grids of 5x5 to 64x64"):
        obs.add_map(grid_msg(65))
    with pytest.raises(ValueError, match="square"):
        msg = grid_msg(17)
        msg.info.width = 15
        msg.data = msg.data[: 17 * 15]
        obs.add_map(msg)


def test_a_whole_grid_observer_refuses_another_size_and_says_what_to_do():
    from medc_agents.team_state import TeamObserver

    obs = TeamObserver("agent_0", 3, 13, observation="maps")
    obs.add_map(grid_msg(13))
    with pytest.raises(ValueError, match=r"17x17.*'maps' shows the whole 13x13 grid.*egoR"):
        obs.add_map(grid_msg(17))


@pytest.mark.timing
@pytest.mark.ros
def test_shipped_team_plays_a_17x17_map_started_from_its_bundle_alone(rclpy_context):
    """The documented start (``-p agent_id:=... -p policy:=<bundle>``, nothing else): the agents take
    grid 13 from the manifest and still play the simulator's 17x17 maps."""
    from medc_agents.node import AgentNode
    from medc_sim.simulator import SimNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    def params(**kw):
        return [Parameter(k, value=v) for k, v in kw.items()]

    sim = SimNode(parameter_overrides=params(agents=3, walls=2, grid=17, max_steps=60, seed=2, episodes=6,
                                             wait_for_subscribers=3))
    agents = [AgentNode(agent_id=f"agent_{i}", parameter_overrides=params(agent_id=f"agent_{i}",
                                                                        policy=str(TEAM)))
              for i in range(3)]
    executor = SingleThreadedExecutor()
    for node in (sim, *agents):
        executor.add_node(node)
    try:
        assert spin_until(executor, lambda: sim.finished, 180), f"only {len(sim.core.results)} episodes"
        assert all(a.observer.memory.grid == 17 and a.dropped == 0 for a in agents)
        found = sum(r.success for r in sim.core.results)
        # Random moves find about a quarter of 17x17 episodes in 60 steps (models/README.md).
        assert found >= 4, [(r.length, r.success) for r in sim.core.results]
    finally:
        executor.shutdown()
        for node in (sim, *agents):
            node.destroy_node()
