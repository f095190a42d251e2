"""The team's estimate outlives agent_0 (medc_agents.estimate.EstimateRole): the lowest-numbered live
agent publishes it. The rule without ROS, then the simulator and three medc-agent processes with
agent_0's process killed mid-run."""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

import pytest
from ros_helpers import start_node_process, stop_node_processes

BIN = Path(sys.executable).parent


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_lowest_numbered_live_agent_holds_the_role():
    from medc_agents.estimate import EstimateRole

    clock = _Clock()
    first = EstimateRole(0, 1.5, clock)
    assert first.holds(0, 0) and first.holds(9, 9)  # agent_0 always publishes

    role = EstimateRole(2, 1.5, clock)  # agent_2
    assert not role.holds(0, 0)  # nobody heard yet, but the run just started
    for step in range(3):
        role.moved(0, 0, step)
        role.moved(1, 0, step)
        clock.t += 0.1
        assert not role.holds(0, step + 1)
    # agent_0 answers no more: while the team waits for it, it is not gone (the driver has not
    # stepped on without it), nor while it is one step behind (its move may be on its way); two
    # steps behind and silent for 1.5 s, it is.
    clock.t += 3.0
    assert not role.holds(0, 3) and not role.holds(0, 4)  # agent_0 answered step 2
    role.moved(1, 0, 3)
    assert role.gone_ids(0, 5) == [0] and not role.holds(0, 5)  # agent_1 lives: it publishes
    clock.t += 3.0
    assert role.holds(0, 6) and role.gone_ids(0, 6) == [0, 1]  # agent_1 silent too: agent_2's turn
    role.moved(0, 0, 6)  # agent_0 is back (a restarted process)
    assert not role.holds(0, 7)
    # A new episode: the steps of the one before are not behind its first two.
    clock.t += 3.0
    role.moved(0, 0, 11)
    clock.t += 1.6
    assert not role.gone(0, 1, 0) and not role.gone(0, 1, 1) and role.gone(0, 1, 2)
    # Never heard from: gone 1.5 s after this agent's first step.
    late = EstimateRole(1, 1.5, clock)
    assert not late.holds(0, 0)
    clock.t += 1.6
    assert late.holds(0, 2)
    # lost_timeout_s 0 (no teammate is ever taken out): the role never passes on.
    assert not EstimateRole(1, 0.0, clock).holds(5, 5)
    # A move from an agent that does not precede this one is none of its business.
    role.moved(2, 9, 9)
    role.moved(7, 9, 9)
    assert set(role.last) == {0, 1}


class _Listener:
    """Records the team's statuses, estimates and the agents' heartbeats (their ``estimate`` value)."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from medc_common import contract
        from medc_interfaces.msg import EpisodeStatus
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node("failover_listener")
        self.estimates: list[tuple[float, tuple[int, int]]] = []
        self.statuses: list = []
        self.roles: dict[str, list[tuple[float, str]]] = {}
        self.node.create_subscription(
            PoseWithCovarianceStamped, contract.estimate_topic("/medc"),
            lambda m: self.estimates.append((time.monotonic(), (m.header.stamp.sec, m.header.stamp.nanosec))),
            contract.ESTIMATE_QOS)
        self.node.create_subscription(EpisodeStatus, contract.status_topic("/medc"), self.statuses.append,
                                      contract.RELIABLE_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics,
                                      QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if "estimate" in values:
                self.roles.setdefault(status.hardware_id, []).append((time.monotonic(), values["estimate"]))

    def spin(self, seconds: float, until, procs) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            assert all(p.poll() is None for p in procs), "a node died"
            if until():
                return True
        return False

    def role(self, agent: str, since: float = 0.0) -> set[str]:
        return {r for t, r in self.roles.get(agent, []) if t >= since}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_the_estimate_goes_on_when_agent_0_is_killed(rclpy_context, bundles, tmp_path):
    """agent_0 publishes while it lives (agent_1 and agent_2 stand by); SIGKILL its process: the
    simulator takes it out after move_timeout_s (its default, 3 s: long enough that no agent busy
    on a loaded machine is taken out meanwhile), and agent_1 publishes the estimate of the steps
    after that, one estimate per step (agent_2 stays on standby)."""
    listen = _Listener()
    logs = {name: tmp_path / f"{name}.log" for name in ("sim", "agent_0", "agent_1", "agent_2")}
    sim = ["agents:=3", "walls:=1", "grid:=10", "max_steps:=30", "seed:=3", "rate_hz:=10.0",
           "wait_for_subscribers:=3"]
    procs = [start_node_process([str(BIN / "medc-sim"), "--ros-args", *[a for p in sim for a in ("-p", p)]],
                                logs["sim"])]
    procs += [start_node_process([str(BIN / "medc-agent"), "--ros-args", "-p", f"agent_id:=agent_{i}",
                                  "-p", "agents:=3", "-p", f"policy:={bundles['a']}"], logs[f"agent_{i}"])
              for i in range(3)]
    try:
        assert listen.spin(180, lambda: len(listen.estimates) >= 10 and {"agent_0", "agent_1", "agent_2"}
                           <= set(listen.roles), procs), "the team did not start publishing its estimate"
        assert listen.role("agent_0") == {"publishing"}
        assert listen.role("agent_1") == listen.role("agent_2") == {"standby"}
        t_kill = time.monotonic()
        procs[1].send_signal(signal.SIGKILL)
        procs[1].wait(10)
        alive = [procs[0], procs[2], procs[3]]
        assert listen.spin(90, lambda: "publishing" in listen.role("agent_1", t_kill), alive), \
            f"agent_1 never took the estimate over:\n{logs['agent_1'].read_text()[-2000:]}"
        t_over = time.monotonic()
        count = len(listen.estimates)
        assert listen.spin(90, lambda: len(listen.estimates) >= count + 10, alive), \
            f"no estimate after agent_0 was killed:\n{logs['agent_1'].read_text()[-2000:]}"
        t_end = time.monotonic()
        after = [stamp for t, stamp in listen.estimates if t_over < t <= t_end]

        def steps() -> set:
            return {(s.header.stamp.sec, s.header.stamp.nanosec) for s in listen.statuses if not s.done}

        # The statuses of the last estimates come in too (another publisher's: no order between them).
        listen.spin(60, lambda: set(after) <= steps(), alive)
        assert set(after) <= steps()  # the estimates of the team's steps ...
        assert len(after) == len(set(after))  # ... one per step: one publisher
        assert listen.role("agent_2", t_kill) == {"standby"}
    finally:
        stop_node_processes(procs)
        listen.close()
    text = logs["agent_1"].read_text()
    assert "agent_0 gone: agent_1 publishes the team's source estimate from episode" in text, text[-2000:]
    assert not any("Traceback" in p.read_text() for p in logs.values())
