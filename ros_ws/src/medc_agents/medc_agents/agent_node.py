"""medc-agent: run one agent node (medc_agents.node.AgentNode) until Ctrl-C.

Usage: ``medc-agent --ros-args -p agent_id:=agent_0 -p policy:=models/team/A3W2.safetensors``:
the team size, grid and observation come from the bundle's manifest. The node is named
``medc_<agent_id>`` (``-r __node:=NAME`` overrides it). A bad parameter (e.g. agent_id agent_7 in
a team of 3) or a policy it cannot run (none, missing, invalid, not fitting) ends it with status 2
and the reason on stderr: an agent never idles without a policy.
"""

from __future__ import annotations

import sys

from medc_common.ros_env import require_interfaces


def agent_id_from_arguments() -> str | None:
    """The ``agent_id`` parameter given on the command line or in a parameter file, read by a
    short-lived probe node (rclpy must be initialised): the node's default name depends on it."""
    import rclpy
    from medc_common.contract import DEFAULT_NAMESPACE

    probe = rclpy.create_node("medc_agent", namespace=DEFAULT_NAMESPACE, start_parameter_services=False,
                              enable_rosout=False)
    try:
        probe.declare_parameter("agent_id", "agent_0")
        value = probe.get_parameter("agent_id").value
        return value if isinstance(value, str) else None
    except Exception:  # a wrongly typed value: AgentNode reports it
        return None
    finally:
        probe.destroy_node()


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-agent``; ``--help`` lists its parameters and exits 0 without starting it."""
    from medc_common.cli_help import print_node_help, wants_help

    if wants_help(argv):
        return print_node_help(
            "medc-agent", "One agent node per UAV: observes the team, runs its policy bundle (or a "
                          "classical controller) and publishes its move; agent_0 also publishes the "
                          "team's source estimate and declaration.",
            ["medc_agents.node", "medc_agents.estimate", "medc_common.auth_node"],
            "medc-agent --ros-args -p agent_id:=agent_0 -p policy:=models/team/A3W2.safetensors")
    require_interfaces()
    from medc_common.executors import run_node

    from medc_agents.node import AgentNode, default_node_name

    def make() -> AgentNode:
        return AgentNode(node_name=default_node_name(agent_id_from_arguments()))

    return run_node("medc-agent", argv, make)


if __name__ == "__main__":
    sys.exit(main())
