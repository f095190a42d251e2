"""The team's estimate outlives agent_0 (medc_agents.estimate.EstimateRole): the lowest-numbered live
agent publishes it. The rule without ROS, then the simulator and three medc-agent processes with
agent_0's process killed mid-run."""

from __future__ import annotations

import os
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
    for step in range(1, 4):
        role.moved(0, 0, step - 1)
        role.moved(1, 0, step - 1)
        clock.t += 0.1
        assert not role.holds(0, step)
    # agent_0 answers no more (its last move: step 2). While the team waits for it at step 3 it is
    # not gone; at step 4 the driver has stepped on without its move for step 3, and none came
    # for 1.5 s: gone from the step after the loss on.
    role.moved(1, 0, 3)
    clock.t += 3.0
    assert role.gone_ids(0, 4) == [0] and not role.holds(0, 4)  # agent_1 moved for step 3: it publishes
    role.moved(1, 0, 4)
    clock.t += 0.1
    assert role.gone_ids(0, 5) == [0]
    clock.t += 3.0
    assert role.holds(0, 6) and role.gone_ids(0, 6) == [0, 1]  # agent_1 silent too: agent_2's turn
    role.moved(0, 0, 6)  # agent_0 is back (a restarted process)
    assert not role.holds(0, 7)
    assert role.gone_ids(0, 7, below=False) == [1]  # every teammate is followed


def test_the_role_stays_with_the_next_agent_across_episodes_and_hands_back():
    from medc_agents.estimate import EstimateRole

    clock = _Clock()
    role = EstimateRole(1, 1.5, clock, num_agents=3)  # agent_1 of 3
    for step in range(5):
        role.moved(0, 0, step)
        role.moved(2, 0, step)
        assert not role.holds(0, step)
        clock.t += 0.1
    # agent_0 answered step 4 and died: step 5 waits 3 s for it (the driver's move timeout), then
    # the driver steps on without it; agent_1 holds the role from step 6 on, and at steps 0 and 1
    # of every episode after it (the previous step is then the last of the episode before).
    assert not role.holds(0, 5)
    clock.t += 3.0
    role.moved(2, 0, 5)
    assert role.holds(0, 6)
    for episode in (1, 2):
        for step in range(4):
            clock.t += 0.1
            assert role.holds(episode, step), (episode, step)
            role.moved(2, episode, step)
    # A move still on its way is for the step before: agent_0 back, answering step 3 of episode 2,
    # is live at step 4 even before its move for step 4 comes.
    role.moved(0, 2, 3)
    assert not role.holds(2, 4)
    # The first step of an episode: a live agent_0 answered the last step of the one before.
    role.moved(0, 2, 4)
    clock.t += 0.1
    assert not role.holds(3, 0)
    # Never heard from (still starting, or its move topic not matched yet): gone 5 x 1.5 s after
    # this agent's first step.
    late = EstimateRole(1, 1.5, clock)
    assert not late.holds(0, 0)
    clock.t += 1.6
    assert not late.holds(0, 2)
    clock.t += 6.0
    assert late.holds(0, 3)
    # lost_timeout_s 0 (no teammate is ever taken out): the role never passes on.
    assert not EstimateRole(1, 0.0, clock).holds(5, 5)
    # A move of this agent itself or of an index outside the team is none of its business.
    role.moved(1, 9, 9)
    role.moved(7, 9, 9)
    assert set(role.last) == {0, 2}


def test_a_ghost_answering_for_a_silent_agent_does_not_take_the_role_back():
    from medc_agents.estimate import EstimateRole

    clock = _Clock()
    role = EstimateRole(1, 1.5, clock, num_agents=2)  # agent_1
    for step in range(3):
        role.moved(0, 0, step, "agent0-run1")
        assert not role.holds(0, step + 1)
        clock.t += 0.1
    clock.t += 3.0  # agent_0 dies after its move for step 2; the driver steps on without it
    assert role.holds(0, 4)
    # A ghost answers for agent_0 under a new sender each step: agent_1 keeps the role.
    for step in range(4, 10):
        role.moved(0, 0, step, f"ghost{step}")
        clock.t += 0.1
        assert role.holds(0, step + 1), step
    # agent_0's own process heard again (its sender): back at once.
    role.moved(0, 0, 10, "agent0-run1")
    assert not role.holds(0, 11)
    clock.t += 3.0
    assert role.holds(0, 12)  # silent again
    # A restarted agent_0 (a new sender) is back once it has moved for two steps.
    role.moved(0, 0, 12, "agent0-run2")
    assert role.holds(0, 13)
    role.moved(0, 0, 13, "agent0-run2")
    assert not role.holds(0, 14)


class _Listener:
    """Records the team's statuses, estimates and every diagnostic status (the agents' heartbeats'
    ``estimate`` value among them)."""

    def __init__(self, ns: str = "/medc") -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from medc_common import contract
        from medc_interfaces.msg import EpisodeStatus
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node("failover_listener")
        self.estimates: list[tuple[float, tuple[int, int]]] = []
        self.statuses: list[tuple[float, object]] = []
        self.roles: dict[str, list[tuple[float, str]]] = {}
        self.diagnostics: list[tuple[float, object]] = []
        self.node.create_subscription(
            PoseWithCovarianceStamped, contract.estimate_topic(ns),
            lambda m: self.estimates.append((time.monotonic(), (m.header.stamp.sec, m.header.stamp.nanosec))),
            contract.ESTIMATE_QOS)
        self.node.create_subscription(EpisodeStatus, contract.status_topic(ns),
                                      lambda m: self.statuses.append((time.monotonic(), m)),
                                      contract.RELIABLE_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics,
                                      QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def _on_diagnostics(self, msg) -> None:
        now = time.monotonic()
        for status in msg.status:
            self.diagnostics.append((now, status))
            values = {kv.key: kv.value for kv in status.values}
            if "estimate" in values:
                self.roles.setdefault(status.hardware_id, []).append((now, values["estimate"]))

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

    def steps(self, since: float) -> list:
        """The step statuses (not the closing ones) of this test's simulator (the session of the
        first status: another graph may share the domain) received from ``since`` on."""
        session = self.statuses[0][1].session if self.statuses else None
        return [m for t, m in self.statuses if t >= since and not m.done and m.session == session]

    def agents_condition(self, agent: str, since: float) -> list:
        """The ``agents`` condition of ``agent``'s node published from ``since`` on (its own status)."""
        return [s for t, s in self.diagnostics if t >= since and s.name == f"medc_{agent}: agents"]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def _stamp(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


@pytest.mark.timing
@pytest.mark.ros
def test_the_estimate_goes_on_when_agent_0_is_killed(rclpy_context, bundles, tmp_path):
    """agent_0 publishes while it lives (agent_1 and agent_2 stand by); SIGKILL its process: the
    simulator takes it out after move_timeout_s (its default, 3 s: long enough that no agent busy
    on a loaded machine is taken out meanwhile) and agent_1 publishes from the step after the loss
    on (the loss step's estimate too): every step has its estimate, steps 0 and 1 of the episodes
    after it included, one per step. agent_1 and agent_2 report agent_0, whose UAV still reports,
    on /diagnostics; started again, agent_0 takes the role back and the reports are OK again."""
    from diagnostic_msgs.msg import DiagnosticStatus

    ns = f"/failover{os.getpid()}"  # another graph on this domain (another test run) stays out
    listen = _Listener(ns)
    logs = {name: tmp_path / f"{name}.log"
            for name in ("sim", "agent_0", "agent_1", "agent_2", "agent_0_again")}
    sim = ["agents:=3", "walls:=1", "grid:=10", "max_steps:=30", "seed:=3", "rate_hz:=10.0",
           "wait_for_subscribers:=3"]

    def agent(i: int, log: str):
        return start_node_process([str(BIN / "medc-agent"), "--ros-args", "-r", f"__ns:={ns}", "-p",
                                   f"agent_id:=agent_{i}", "-p", "agents:=3", "-p",
                                   f"policy:={bundles['a']}"],
                                  logs[log])

    procs = [start_node_process([str(BIN / "medc-sim"), "--ros-args", "-r", f"__ns:={ns}",
                                 *[a for p in sim for a in ("-p", p)]], logs["sim"])]
    procs += [agent(i, f"agent_{i}") for i in range(3)]
    try:
        # The statuses too: the kill below is placed after the last step status heard, and on a
        # loaded machine the status subscription can match after the estimates have come in.
        assert listen.spin(180, lambda: len(listen.estimates) >= 10 and bool(listen.steps(0.0))
                           and {"agent_0", "agent_1", "agent_2"} <= set(listen.roles), procs), \
            "the team did not start publishing its estimate and its step statuses"
        assert listen.role("agent_0") == {"publishing"}
        assert listen.role("agent_1") == listen.role("agent_2") == {"standby"}
        # Every step from the one in play when agent_0 dies: the last status heard before the kill.
        t_before = max(t for t, m in listen.statuses if m.session == listen.statuses[0][1].session)
        t_kill = time.monotonic()
        procs[1].send_signal(signal.SIGKILL)
        procs[1].wait(10)
        alive = [procs[0], procs[2], procs[3]]
        assert listen.spin(90, lambda: "publishing" in listen.role("agent_1", t_kill), alive), \
            f"agent_1 never took the estimate over:\n{logs['agent_1'].read_text()[-2000:]}"

        def episodes_begun() -> int:  # episodes whose steps 0 and 1 came after the kill
            firsts = {m.episode for m in listen.steps(t_kill) if m.step == 1}
            return len(firsts & {m.episode for m in listen.steps(t_kill) if m.step == 0})

        assert listen.spin(120, lambda: episodes_begun() >= 2, alive), \
            f"the team stopped after agent_0 was killed:\n{logs['sim'].read_text()[-2000:]}"
        wanted = {_stamp(m) for m in listen.steps(t_before)}
        published = lambda: {stamp for _, stamp in listen.estimates}  # noqa: E731
        # The estimates of the last steps come in too (another publisher's: no order between them).
        listen.spin(60, lambda: wanted <= published(), alive)
        missing = sorted((m.episode, m.step) for m in listen.steps(t_before) if _stamp(m) not in published())
        assert not missing, f"steps without an estimate: {missing}\n{logs['agent_1'].read_text()[-2000:]}"
        after = [stamp for t, stamp in listen.estimates if t > t_kill and stamp in wanted]
        assert len(after) - len(set(after)) <= 1, "one estimate per step (the loss step's may come twice)"
        assert listen.role("agent_2", t_kill) == {"standby"}
        # agent_0's UAV still reports: its teammates say on /diagnostics that it does not move.
        for name in ("agent_1", "agent_2"):
            warned = [s for s in listen.agents_condition(name, t_kill) if s.level == DiagnosticStatus.WARN]
            assert warned and all("agent_0" in s.message and "its UAV still reports" in s.message
                                  for s in warned), name
            # One fault, one message (the heartbeat repeats it).
            assert len({s.message for s in warned}) == 1, [s.message for s in warned]

        # agent_0 starts again: it takes the role back and the reports are OK again.
        t_back = time.monotonic()
        procs.append(agent(0, "agent_0_again"))
        alive.append(procs[-1])
        ok = lambda name: any(s.level == DiagnosticStatus.OK  # noqa: E731
                              for s in listen.agents_condition(name, t_back))
        assert listen.spin(180, lambda: ok("agent_1") and ok("agent_2")
                           and listen.role("agent_1", time.monotonic() - 1.5) == {"standby"}, alive), \
            f"agent_0 did not come back:\n{logs['agent_1'].read_text()[-2000:]}"
    finally:
        stop_node_processes(procs)
        listen.close()
    text = logs["agent_1"].read_text()
    handover = "agent_0 gone: agent_1 publishes the team's source estimate from episode"
    assert text.count(handover) == 1, text[-3000:]
    for name in ("agent_1", "agent_2"):  # the fault is logged once, and its end once
        text = logs[name].read_text()
        assert text.count("no move while its UAV still reports") == 1, text[-3000:]
        assert text.count(f"every teammate of {name} moves") == 1, text[-3000:]
    assert not any("Traceback" in p.read_text() for p in logs.values() if p.exists())
