"""Faults on /diagnostics (docs/ros-reference.md, "Diagnostics"): one agent node and the simulator, each in
this process with a hand-written counterpart, show each fault once, with its reason, and OK again
when it clears; what the contract calls normal (a status below the step answered) is counted, not
warned."""

from __future__ import annotations

import pytest
import torch
from builtin_interfaces.msg import Time
from ros_helpers import spin_until

NS = "/medc"


def _params(**kw):
    from rclpy.parameter import Parameter

    return [Parameter(k, value=v) for k, v in kw.items()]


class _Seen:
    """What a test node hears: the moves of agent_0 and every diagnostic status."""

    def __init__(self, node) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from medc_common import contract
        from medc_interfaces.msg import AgentMove
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.moves: list = []
        self.diagnostics: list = []
        self.move_sub = node.create_subscription(AgentMove, contract.move_topic(NS, "agent_0"),
                                                 self.moves.append, contract.RELIABLE_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.diagnostics.extend(m.status),
                                 QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))

    def moved(self, episode: int, step: int) -> bool:
        return any((m.episode, m.step) == (episode, step) for m in self.moves)

    def condition(self, name: str) -> list:
        """The statuses of condition ``name`` (e.g. 'medc_agent_0: map'), in arrival order."""
        return [s for s in self.diagnostics if s.name == name]

    def last(self, name: str):
        got = self.condition(name)
        return got[-1] if got else None


class _Log:
    """The node logs this process wrote to stderr (rclpy logs there), gathered across reads."""

    def __init__(self, capfd) -> None:
        self.capfd = capfd
        self.text = ""

    def __call__(self) -> str:
        self.text += self.capfd.readouterr().err
        return self.text


@pytest.mark.timing
@pytest.mark.ros
def test_an_agent_names_a_refused_map_takes_a_new_area_and_counts_old_statuses(rclpy_context, capfd,
                                                                                monkeypatch):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from geometry_msgs.msg import PoseStamped
    from medc_agents import node as agent_node
    from medc_agents.node import AgentNode
    from medc_common import contract
    from medc_common.contract import GridGeometry
    from medc_interfaces.msg import EpisodeStatus, RadiationReading
    from medc_sim import messages
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor

    monkeypatch.setattr(agent_node, "OLD_STATUS_SUMMARY_S", 0.5)
    agent = AgentNode(agent_id="agent_0", parameter_overrides=_params(
        agent_id="agent_0", policy="greedy", agents=1, grid=10, stall_timeout_s=1.0))
    driver = rclpy.create_node("fault_driver", namespace=NS)
    seen = _Seen(driver)
    pose_pub = driver.create_publisher(PoseStamped, contract.pose_topic(NS, "agent_0"), contract.SENSOR_QOS)
    reading_pub = driver.create_publisher(RadiationReading, contract.radiation_topic(NS, "agent_0"),
                                          contract.SENSOR_QOS)
    status_pub = driver.create_publisher(EpisodeStatus, contract.status_topic(NS), contract.RELIABLE_QOS)
    map_pub = driver.create_publisher(OccupancyGrid, contract.map_topic(NS), contract.LATCHED_QOS)
    executor = SingleThreadedExecutor()
    for node in (agent, driver):
        executor.add_node(node)
    log = _Log(capfd)
    ids = ["agent_0"]
    home = GridGeometry(10, 10)
    far = GridGeometry(10, 10, 1.0, 500.0, 500.0)

    def publish_map(sec: int, side: int = 10, origin: float = 0.0) -> None:
        msg = messages.grid_msg(torch.zeros((side, side), dtype=torch.bool), Time(sec=sec), 1.0)
        msg.info.origin.position.x = msg.info.origin.position.y = origin
        map_pub.publish(msg)

    def publish_step(episode: int, step: int, sec: int, map_sec: int, geo=home) -> None:
        stamp = Time(sec=sec)
        pose_pub.publish(messages.pose_msg((step % 10, 2), stamp, geo))
        reading_pub.publish(messages.reading_msg("agent_0", 2.0, 0.0, stamp))
        status_pub.publish(messages.status_msg(ids, episode, step, stamp, Time(sec=map_sec), session="s1"))

    try:
        assert spin_until(executor, lambda: min(p.get_subscription_count() for p in
                                                (pose_pub, reading_pub, status_pub, map_pub)) >= 1
                          and seen.move_sub.get_publisher_count() >= 1, 30)
        publish_map(1)
        for step in range(3):
            publish_step(0, step, 10 + step, 1)
            assert spin_until(executor, lambda s=step: seen.moved(0, s), 30), f"no move for step {step}"

        # Statuses below the step answered (re-sends that crossed the next step): counted, summed up
        # in one line, never a warning.
        for _ in range(3):
            status_pub.publish(messages.status_msg(ids, 0, 1, Time(sec=11), Time(sec=1), session="s1"))
        summed = lambda: "statuses below the step answered dropped" in log()  # noqa: E731
        assert spin_until(executor, summed, 30), log()[-2000:]
        assert agent.dropped_by["old status"] == 3 and agent._summary()["old_statuses"] == "3"
        assert "3 statuses below the step answered dropped" in log()
        assert "dropped status" not in log() and agent.health.level("status") == DiagnosticStatus.OK

        # A refused map (4x4: no agent plays it): WARN with the reason; the step naming it stalls, and
        # its stall report gives that reason, not the maps held. The map sent right: both OK again.
        publish_map(20, side=4)
        assert spin_until(executor, lambda: seen.last("medc_agent_0: map") is not None, 30)
        refused = seen.last("medc_agent_0: map")
        assert refused.level == DiagnosticStatus.WARN
        assert refused.message.startswith("map with map_load_time 20.000000000 refused: map is 4x4"), \
            refused.message
        publish_step(1, 0, 21, 20)
        stalled = lambda: seen.last("medc_agent_0: team step")  # noqa: E731
        assert spin_until(executor, lambda: stalled() is not None, 30)
        assert stalled().level == DiagnosticStatus.WARN
        assert "have: that map was refused: map is 4x4" in stalled().message, stalled().message
        assert "maps with info.map_load_time" not in stalled().message
        publish_map(20)
        assert spin_until(executor, lambda: seen.moved(1, 0), 30), "the step did not go on with the right map"
        assert spin_until(executor, lambda: seen.last("medc_agent_0: map").level == DiagnosticStatus.OK
                          and stalled().level == DiagnosticStatus.OK, 30)
        assert log().count("map_load_time 20.000000000 refused") == 1  # once per fault

        # A new area 500 m away: its map, then its first poses; nothing dropped, no re-send needed,
        # no warning that the map holds none of the team's poses.
        publish_map(30, origin=500.0)
        publish_step(2, 0, 31, 30, far)
        assert spin_until(executor, lambda: seen.moved(2, 0), 30), agent.observer.waiting_for()
        # The poses come first and their map after them (it is on its way): they are held until
        # the status names the map, then checked against it.
        publish_step(3, 0, 41, 40, home)
        publish_map(40)
        assert spin_until(executor, lambda: seen.moved(3, 0), 30), agent.observer.waiting_for()
        spin_until(executor, lambda: False, 1.5)  # the map check runs 1 s after a map no status named
        assert agent.dropped_by["pose"] == 0 and "dropped pose" not in log()
        assert not [s for s in seen.condition("medc_agent_0: map") if "holds none" in s.message]
        assert "Traceback" not in log()
    finally:
        executor.shutdown()
        for node in (agent, driver):
            node.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_the_simulator_reports_two_moves_of_one_sender_with_different_actions(rclpy_context, capfd,
                                                                               monkeypatch):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from medc_common import contract
    from medc_interfaces.msg import AgentMove, EpisodeStatus
    from medc_sim import move_watch
    from medc_sim.simulator import SimNode
    from rclpy.executors import SingleThreadedExecutor

    monkeypatch.setattr(move_watch, "FAULT_REPEAT_S", 2.0)
    sim = SimNode(parameter_overrides=_params(agents=1, walls=0, grid=10, max_steps=100, seed=1,
                                              wait_for_subscribers=1))
    agent = rclpy.create_node("conflicting_agent", namespace=NS)
    seen = _Seen(agent)
    statuses: list = []
    agent.create_subscription(EpisodeStatus, contract.status_topic(NS), statuses.append,
                              contract.RELIABLE_QOS)
    move_pub = agent.create_publisher(AgentMove, contract.move_topic(NS, "agent_0"), contract.RELIABLE_QOS)
    executor = SingleThreadedExecutor()
    for node in (sim, agent):
        executor.add_node(node)
    log = _Log(capfd)

    def answer(action: int, then: int) -> None:
        """Answer the latest step twice from one sender: ``action``, then ``then``."""
        s = statuses[-1]
        for a in (action, then):
            move_pub.publish(AgentMove(agent_id="agent_0", episode=s.episode, step=s.step, action=a,
                                       sender="aaaa"))

    moves = lambda: seen.condition("medc_sim: moves")  # noqa: E731
    try:
        assert spin_until(executor, lambda: any(not s.done for s in statuses), 30)
        first = statuses[-1]
        answer(2, 5)
        assert spin_until(executor, lambda: bool(moves()), 30)
        warned = moves()[0]
        assert warned.level == DiagnosticStatus.WARN
        assert warned.message == (
            f"conflicting moves: agent_0 (sender aaaa) sent two moves for episode {first.episode} step "
            f"{first.step} with different actions (2, then 5): the first (2) "
            f"{'is' if sim.book.step == first.step else 'was'} executed, the second ignored; an agent must "
            "re-send the same move"), warned.message
        # The same fault on the next steps: the latest on /diagnostics, one log line, repeats summed up.
        for _ in range(3):
            n = len(statuses)
            assert spin_until(executor, lambda n=n: len(statuses) > n, 30)
            answer(1, 6)
        assert spin_until(executor, lambda: sim.book.conflicts >= 4, 30)
        assert spin_until(executor, lambda: moves()[-1].level == DiagnosticStatus.OK, 30), \
            [s.message for s in moves()]
        summed = lambda: "conflict agent_0: 3 more in the last" in log()  # noqa: E731
        assert spin_until(executor, summed, 30), log()[-2000:]
        assert log().count("conflicting moves: agent_0") == 1, log()[-3000:]
        assert sim._summary()["conflicting_moves"] == "4"
        assert "Traceback" not in log()
    finally:
        executor.shutdown()
        for node in (sim, agent):
            node.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_a_pose_stamped_far_ahead_keeps_no_teammate_in_the_team(rclpy_context, capfd):
    """agent_1's UAV falls silent: agent_0 takes it out after lost_timeout_s, even while a pose and
    reading of agent_1 stamped an hour ahead come (no sign of life), and they do not take it back;
    its pose and reading of the step waited on do."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from medc_agents.node import AgentNode
    from medc_common import contract
    from medc_common.contract import GridGeometry
    from medc_interfaces.msg import EpisodeStatus, RadiationReading
    from medc_sim import messages
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor

    ids = ["agent_0", "agent_1"]
    agent = AgentNode(agent_id="agent_0", parameter_overrides=_params(
        agent_id="agent_0", policy="greedy", agents=2, grid=10, lost_timeout_s=0.5))
    driver = rclpy.create_node("stamp_driver", namespace=NS)
    seen = _Seen(driver)
    pubs = {(kind, a): driver.create_publisher(t, topic(NS, a), contract.SENSOR_QOS)
            for a in ids for kind, t, topic in (("pose", PoseStamped, contract.pose_topic),
                                                ("reading", RadiationReading, contract.radiation_topic))}
    status_pub = driver.create_publisher(EpisodeStatus, contract.status_topic(NS), contract.RELIABLE_QOS)
    map_pub = driver.create_publisher(OccupancyGrid, contract.map_topic(NS), contract.LATCHED_QOS)
    executor = SingleThreadedExecutor()
    for node in (agent, driver):
        executor.add_node(node)
    log = _Log(capfd)
    geo = GridGeometry(10, 10)

    def send(a: str, sec: int, cell=(5, 5)) -> None:
        pubs[("pose", a)].publish(messages.pose_msg(cell, Time(sec=sec), geo))
        pubs[("reading", a)].publish(messages.reading_msg(a, 2.0, 0.0, Time(sec=sec)))

    def step(n: int, who=("agent_0", "agent_1")) -> None:
        for a in who:
            send(a, 10 + n, (n % 10, ids.index(a)))
        status_pub.publish(messages.status_msg(ids, 0, n, Time(sec=10 + n), Time(sec=1), session="s1"))

    try:
        everyone = (*pubs.values(), status_pub, map_pub)
        assert spin_until(executor, lambda: min(p.get_subscription_count() for p in everyone) >= 1
                          and seen.move_sub.get_publisher_count() >= 1, 30)
        map_pub.publish(messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0))
        step(0)
        assert spin_until(executor, lambda: seen.moved(0, 0), 30)
        # agent_1's UAV falls silent; a pose and reading of it stamped an hour ahead come meanwhile.
        step(1, who=("agent_0",))
        send("agent_1", 10 + 3600)
        assert spin_until(executor, lambda: seen.moved(0, 1), 30), agent.observer.waiting_for()
        assert agent.observer.absent == {1} and "agent_1 lost" in log()
        step(2, who=("agent_0",))
        send("agent_1", 10 + 3601)
        assert spin_until(executor, lambda: seen.moved(0, 2), 30)
        assert agent.observer.absent == {1} and "agent_1 is heard again" not in log()
        # Its pose and reading of the step waited on take it back.
        step(3)
        assert spin_until(executor, lambda: seen.moved(0, 3), 30)
        assert agent.observer.absent == set() and log().count("agent_1 is heard again: back in the team") == 1
        assert "Traceback" not in log()
    finally:
        executor.shutdown()
        for node in (agent, driver):
            node.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_a_declaration_counts_only_from_a_team_member(rclpy_context, capfd):
    """Under end_on: declaration, the simulator refuses a declaration naming no agent of the team,
    and every declaration while a node that moves no agent publishes declarations (a message does
    not say which node sent it); each refusal is on /diagnostics with its reason. Once that node is
    gone, the team's declaration ends the episode and the report is OK again."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from medc_common import contract
    from medc_interfaces.msg import AgentMove, EpisodeStatus, SourceDeclaration
    from medc_sim.simulator import SimNode
    from rclpy.executors import SingleThreadedExecutor

    sim = SimNode(parameter_overrides=_params(agents=1, walls=0, grid=10, max_steps=200, seed=1,
                                              end_on="declaration", wait_for_subscribers=1))
    member = rclpy.create_node("medc_agent_0", namespace=NS)
    seen = _Seen(member)
    statuses: list = []
    move_pub = member.create_publisher(AgentMove, contract.move_topic(NS, "agent_0"),
                                       contract.RELIABLE_QOS)
    topic = contract.declaration_topic(NS)
    declare_pub = member.create_publisher(SourceDeclaration, topic, contract.RELIABLE_QOS)

    def on_status(msg) -> None:
        statuses.append(msg)
        if not msg.done:  # the member moves north, then south: the episode never ends on its own
            move_pub.publish(AgentMove(agent_id="agent_0", episode=msg.episode, step=msg.step,
                                       action=0 if msg.step % 2 == 0 else 4, sender="member"))

    member.create_subscription(EpisodeStatus, contract.status_topic(NS), on_status, contract.RELIABLE_QOS)
    intruder = rclpy.create_node("intruder", namespace=NS)
    forge_pub = intruder.create_publisher(SourceDeclaration, topic, contract.RELIABLE_QOS)
    executor = SingleThreadedExecutor()
    for node in (sim, member, intruder):
        executor.add_node(node)
    log = _Log(capfd)

    def declaration(agent_id: str):
        s = next(m for m in reversed(statuses) if not m.done)
        return SourceDeclaration(agent_id=agent_id, episode=s.episode, step=s.step, map_stamp=s.map_stamp,
                                 cell_i=0, cell_j=0)

    refused = lambda text: [s for s in seen.condition("medc_sim: declarations")  # noqa: E731
                            if s.level == DiagnosticStatus.WARN and text in s.message]
    try:
        assert spin_until(executor, lambda: len(statuses) >= 3 and sim.count_publishers(topic) >= 2, 30)
        forge_pub.publish(declaration("agent_0"))  # a node that moves no agent, naming agent_0
        assert spin_until(executor, lambda: bool(refused("1 node(s) that move no agent publish on")), 30)
        assert "/medc/intruder" in refused("move no agent")[0].message
        declare_pub.publish(declaration("agent_7"))
        named = "it names 'agent_7', not an agent of this team"
        assert spin_until(executor, lambda: bool(refused(named)), 30)
        assert not any(s.done for s in statuses)  # nothing ended the episode
        # The intruder leaves: the member's declaration ends the episode.
        executor.remove_node(intruder)
        intruder.destroy_node()
        assert spin_until(executor, lambda: sim.count_publishers(topic) == 1, 30)
        declare_pub.publish(declaration("agent_0"))
        reports = lambda: seen.condition("medc_sim: declarations")  # noqa: E731
        assert spin_until(executor, lambda: any(s.done for s in statuses), 30), [s.message for s in reports()]
        assert spin_until(executor, lambda: reports()[-1].level == DiagnosticStatus.OK, 30)
        assert "ended by the team's declaration" in log() and "Traceback" not in log()
    finally:
        executor.shutdown()
        for node in (sim, member):
            node.destroy_node()
