"""The node scripts' ``--help`` (medc_common.cli_help) reads the parameter declarations from the
source; the running nodes declare exactly the names it lists."""

from __future__ import annotations

from pathlib import Path

import pytest

TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"


@pytest.mark.ros
def test_node_help_lists_exactly_the_parameters_the_nodes_declare(rclpy_context):
    from medc_agents.node import AgentNode
    from medc_common.cli_help import declared_parameters
    from medc_sim.simulator import SimNode
    from rclpy.parameter import Parameter

    agent = AgentNode(agent_id="agent_0", parameter_overrides=[Parameter("policy", value=str(TEAM))])
    nodes = {("medc_sim.simulator", "medc_common.auth_node"): SimNode(),
             ("medc_agents.node", "medc_agents.estimate", "medc_common.auth_node"): agent}
    try:
        for modules, node in nodes.items():
            declared = set(node._parameters) - {"use_sim_time", "start_type_description_service"}
            listed = {name for name, _, _ in declared_parameters(*modules)}
            assert listed == declared, (modules, listed ^ declared)
            # The defaults shown are the values a node gets when nothing is set (policy aside).
            for name, default, _ in declared_parameters(*modules):
                if name not in ("policy", "wait_for_subscribers"):
                    assert default == repr(node.get_parameter(name).value), (name, default)
    finally:
        for node in nodes.values():
            node.destroy_node()
