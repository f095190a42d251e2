"""medc-agent: run one agent node (medc_agents.node.AgentNode) until Ctrl-C.

Usage: ``medc-agent --ros-args -p agent_id:=agent_0 -p policy:=models/team/agent.safetensors``.
"""

from __future__ import annotations

import sys

from medc_sim.ros_env import require_interfaces


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-agent``. A bad parameter (e.g. agent_id agent_7 in a team of 3)
    ends it with status 2."""
    require_interfaces()
    from medc_sim.executors import run_node

    from medc_agents.node import AgentNode

    return run_node("medc-agent", argv, AgentNode)


if __name__ == "__main__":
    sys.exit(main())
