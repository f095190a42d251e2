"""medc-agent: run one agent node (medc_agents.node.AgentNode) until Ctrl-C.

Usage: ``medc-agent --ros-args -p agent_id:=agent_0 -p policy:=models/team/agent.safetensors``.
"""

from __future__ import annotations

import signal
import sys

from medc_sim.ros_env import require_interfaces


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-agent``."""
    require_interfaces()
    import rclpy
    from medc_sim.executors import make_executor
    from rclpy.executors import ExternalShutdownException

    from medc_agents.node import AgentNode

    rclpy.init(args=sys.argv if argv is None else argv)
    node = None
    try:
        node = AgentNode()
        executor = make_executor()
        executor.add_node(node)
        # spin_once in a loop (not spin()): Ctrl-C and the launcher's SIGINT are seen within 0.1 s.
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:  # a parameter out of range, e.g. agent_id agent_7 in a team of 3
        print(f"medc-agent: {exc}", file=sys.stderr)
        return 2
    finally:
        # A second Ctrl-C (or the launcher's SIGINT) must not cut the clean-up short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
