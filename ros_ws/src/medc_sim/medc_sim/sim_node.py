"""medc-sim: run the simulator node (medc_sim.simulator.SimNode) until Ctrl-C or ``episodes`` done.

Usage: ``medc-sim --ros-args -p agents:=3 -p seed:=0 --params-file config/sim.yaml``.
"""

from __future__ import annotations

import sys
import time

from medc_common.ros_env import require_interfaces

#: How long a finished simulator waits for a reader of its episode results before exiting.
RESULTS_READER_WAIT_S = 15.0


def spin_episodes(node, executor) -> None:
    """Spin until the requested episodes are done (or shutdown), then let readers collect the
    results before the process exits."""
    from medc_common.executors import running

    while running() and not node.finished:
        executor.spin_once(timeout_sec=0.1)
    # The episode results are latched, but only while this process lives: a reader that is
    # still being discovered (a loaded machine can take seconds) would miss them all. Wait
    # (bounded) for the results readers the start gate expects (at least one; a recorder alone
    # must not end the wait for the launcher's monitor), then linger so reliable resends complete.
    readers = max(1, node.gate.results_readers)
    deadline = time.monotonic() + RESULTS_READER_WAIT_S
    while running() and node.results_pub.get_subscription_count() < readers and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    linger = time.monotonic() + 1.0
    while running() and time.monotonic() < linger:
        executor.spin_once(timeout_sec=0.1)


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-sim``: run the simulator node until Ctrl-C (or ``episodes`` done);
    ``--help`` lists its parameters and exits 0 without starting it."""
    from medc_common.cli_help import print_node_help, wants_help

    if wants_help(argv):
        return print_node_help(
            "medc-sim", "The simulator node: plays the UAV team's drivers (poses, readings, the walls map, "
                        "the episode status) and applies the agents' moves.",
            ["medc_sim.simulator", "medc_common.auth_node"],
            "medc-sim --ros-args -p agents:=3 -p grid:=13 -p seed:=0")
    require_interfaces()
    from medc_common.executors import run_node

    from medc_sim.simulator import SimNode

    return run_node("medc-sim", argv, SimNode, spin=spin_episodes)


if __name__ == "__main__":
    sys.exit(main())
