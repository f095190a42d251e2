"""Recording a MEDC graph (medc-record, medc-launch --record): rosbag2's MCAP layout that
``rosbags`` and ``mcap_ros2`` decode, topics found as they appear, and a recorder that never
counts as an agent at the simulator's start gate."""

from __future__ import annotations

import json
import re
import subprocess
import time
from pathlib import Path

import pytest
from ros_helpers import spin_until

REPO = Path(__file__).resolve().parents[2]


def _launch(args: list[str], tmp_path: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    """Run medc-launch; on timeout its nodes are stopped too (ros_helpers.stop_launcher)."""
    from ros_helpers import run_launcher

    err = tmp_path / "stderr.txt"
    try:
        code, out = run_launcher(args, tmp_path, timeout, err)
    except subprocess.TimeoutExpired:
        pytest.fail(f"medc-launch did not finish in {timeout:.0f} s:\n{err.read_text()[-3000:]}")
    assert code == 0, err.read_text()[-3000:]
    return subprocess.CompletedProcess(args, code, out)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("mode", [
    [],
    ["--in-process"],
], ids=["processes", "in-process"])
@pytest.mark.timing
def test_launch_record_decodes_to_the_episodes_it_printed(bundles, tmp_path, mode):
    """An MCAP from ``medc-launch --record`` holds the episodes ``--episodes`` printed, readable
    by rosbags and mcap_ros2, custom medc_interfaces types included."""
    from mcap.reader import make_reader
    from mcap_ros2.reader import read_ros2_messages
    from rosbags.highlevel import AnyReader

    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 1\nmax_steps: 20\nseed: 3\npolicy: {bundles['a']}\n")
    # --timeout: a graph that stalls ends with the launcher's own failure, well before the test's.
    out = _launch(["--config", str(config), "--episodes", "3", "--record", "run.mcap", "--timeout", "120",
                   *mode], tmp_path)
    printed = [(int(e), int(n), v == "target found")
               for e, n, v in re.findall(r"^episode (\d+): (\d+) steps, (target found|truncated)$",
                                         out.stdout, flags=re.M)]
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(printed) == 3 and summary["episodes"] == 3
    recording = summary["recording"]
    assert recording["output"] == str(tmp_path / "run.mcap") and recording["messages"] > 0
    assert recording["per_message_us"] is not None and recording["per_message_us"] > 0

    path = tmp_path / "run.mcap"
    with path.open("rb") as f:
        reader = make_reader(f)
        header, summ = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {s.encoding for s in summ.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summ.channels.values()} == {"cdr"}
    topics = {c.topic for c in summ.channels.values()}
    for agent in ("agent_0", "agent_1", "agent_2"):
        assert {f"/medc/{agent}/pose", f"/medc/{agent}/radiation", f"/medc/{agent}/move"} <= topics

    # mcap_ros2: the results and the closing statuses are the printed episodes.
    results, done, readings, moves = [], [], {}, {}
    for m in read_ros2_messages(str(path)):
        topic = m.channel.topic
        if topic == "/medc/episode_result":
            results.append((m.ros_msg.episode, m.ros_msg.episode_length, m.ros_msg.success))
        elif topic == "/medc/episode" and m.ros_msg.done:
            done.append((m.ros_msg.episode, m.ros_msg.episode_length, m.ros_msg.success))
        elif topic.endswith("/radiation"):
            readings[topic] = readings.get(topic, 0) + 1
            assert m.ros_msg.header.frame_id == "map" and m.ros_msg.value >= 0
        elif topic.endswith("/move"):
            moves.setdefault(topic, set()).add((m.ros_msg.episode, m.ros_msg.step))
    assert sorted(results) == printed  # RESULTS_QOS keeps 1000: complete in either mode
    steps = sum(n for _, n, _ in printed)
    assert sorted(moves) == [f"/medc/agent_{i}/move" for i in range(3)]
    assert len(readings) == 3 and all(n > 0 for n in readings.values())
    if not mode:
        # Processes: the team steps at the agents' pace, and a reliable topic (status, moves; keep
        # last 20) reaches the recorder whole. In one process the team can outrun a recorder in
        # another by more than 20 messages on a loaded machine (docs/ros-guide.md, "Record, watch,
        # export", says so). Readings are best effort (sensor-data QoS, as a driver publishes
        # them): any reader may miss some.
        assert sorted(set(done)) == printed
        counts = {t: len(v) for t, v in moves.items()}
        assert all(n == steps for n in counts.values()), counts

    # rosbags: every message of every topic deserialises; the episodes again.
    with AnyReader([path]) as bag:
        assert "medc_interfaces/msg/AgentMove" in {c.msgtype for c in bag.connections}
        count, episodes = 0, []
        for conn, _, raw in bag.messages():
            msg = bag.deserialize(raw, conn.msgtype)
            count += 1
            if conn.topic == "/medc/episode_result":
                episodes.append((msg.episode, msg.episode_length, msg.success))
            if conn.topic.endswith("/move"):
                assert 0 <= msg.action <= 7
    assert sorted(episodes) == printed
    assert count == recording["messages"]


def test_schema_text_embeds_every_type_it_uses():
    from medc_bringup.recording import message_definition

    text = message_definition("medc_interfaces/msg/EpisodeStatus")
    assert text.startswith("# The simulator's clock tick")
    assert "\nMSG: std_msgs/Header\n" in text and "\nMSG: builtin_interfaces/Time\n" in text
    assert text.count("MSG: builtin_interfaces/Time") == 1  # used twice, embedded once
    grid = message_definition("nav_msgs/msg/OccupancyGrid")
    assert "MSG: nav_msgs/MapMetaData" in grid and "MSG: geometry_msgs/Pose" in grid
    with pytest.raises(ValueError, match="build_interfaces"):
        message_definition("no_such_msgs/msg/Thing")


@pytest.mark.timing
@pytest.mark.ros
def test_recorder_finds_topics_that_appear_later(rclpy_context, tmp_path):
    """A topic another node adds under the namespace after the recorder started (the team's
    estimate) is recorded; one outside the namespace is not."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from mcap_ros2.reader import read_ros2_messages
    from medc_bringup.recorder import make_recorder_node
    from medc_bringup.recording import McapRecording
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    path = tmp_path / "late.mcap"
    recording = McapRecording(path)
    recorder = make_recorder_node("/rt", recording, discover_every_s=0.1)
    other = rclpy.create_node("late_publisher")
    executor = SingleThreadedExecutor()
    executor.add_node(recorder)
    executor.add_node(other)
    try:
        spin_until(executor, lambda: False, 0.3)
        estimate_pub = other.create_publisher(PoseWithCovarianceStamped, "/rt/team/estimate", 10)
        foreign_pub = other.create_publisher(String, "/elsewhere/chatter", 10)
        assert spin_until(executor, lambda: "/rt/team/estimate" in recorder.subscribed, 60.0)
        assert spin_until(executor, lambda: estimate_pub.get_subscription_count() > 0, 60.0)
        msg = PoseWithCovarianceStamped()
        msg.header.frame_id = "map"
        msg.pose.pose.position.x = 4.5
        for _ in range(3):
            estimate_pub.publish(msg)
            foreign_pub.publish(String(data="not ours"))
        assert spin_until(executor, lambda: recording.counts.get("/rt/team/estimate", 0) >= 3, 60.0)
    finally:
        executor.shutdown()
        recorder.destroy_node()
        other.destroy_node()
        recording.close()
    assert "/elsewhere/chatter" not in recorder.subscribed
    got = [m.ros_msg.pose.pose.position.x for m in read_ros2_messages(str(path))
           if m.channel.topic == "/rt/team/estimate"]
    assert got == [4.5, 4.5, 4.5]


@pytest.mark.timing
@pytest.mark.ros
def test_a_recorder_does_not_start_the_simulator(rclpy_context):
    """The start gate counts the agents' own move publishers: two status subscribers that are
    recorders do not start a two-agent simulator; the agents' move publishers do."""
    import rclpy
    from medc_interfaces.msg import AgentMove, EpisodeStatus
    from medc_sim.simulator import SimNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    ns = "/gate"
    sim = SimNode(parameter_overrides=[Parameter("namespace", value=ns), Parameter("agents", value=2),
                                       Parameter("grid", value=8), Parameter("walls", value=0),
                                       Parameter("wait_for_subscribers", value=2)])
    recorders = rclpy.create_node("recorders")
    for _ in range(2):
        recorders.create_subscription(EpisodeStatus, f"{ns}/episode", lambda m: None, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(sim)
    executor.add_node(recorders)
    try:
        assert spin_until(executor, lambda: sim.status_pub.get_subscription_count() >= 2, 60.0)
        spin_until(executor, lambda: sim.started, 1.5)
        assert not sim.started, "two recorders started the simulator without its agents"
        agents = rclpy.create_node("agents")
        executor.add_node(agents)
        agents.create_publisher(AgentMove, f"{ns}/agent_0/move", 10)
        spin_until(executor, lambda: sim.started, 1.0)
        assert not sim.started, "one agent of two started the simulator"
        agents.create_publisher(AgentMove, f"{ns}/agent_1/move", 10)
        assert spin_until(executor, lambda: sim.started, 60.0)
        agents.destroy_node()
    finally:
        executor.shutdown()
        sim.destroy_node()
        recorders.destroy_node()


@pytest.mark.timing
@pytest.mark.ros
def test_the_recorder_listens_to_the_status_once_it_hears_the_team(rclpy_context):
    """With --agents the recorder subscribes to the episode status (what the simulator's start gate
    counts) only once its subscriptions to the map and to every agent's pose, reading and move
    have had a publisher for HOLD_SETTLE_S, so the first step waits until it hears every agent;
    after hold_status_s it subscribes anyway."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from medc_bringup.recorder import HOLD_SETTLE_S, make_recorder_node
    from medc_common import contract
    from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor

    ns = "/hold"
    recorder = make_recorder_node(ns, agents=2, discover_every_s=0.05)
    driver = rclpy.create_node("hold_driver")
    executor = SingleThreadedExecutor()
    nodes = [recorder, driver]
    for node in nodes:
        executor.add_node(node)
    try:
        driver.create_publisher(EpisodeStatus, f"{ns}/episode", contract.RELIABLE_QOS)
        driver.create_publisher(OccupancyGrid, f"{ns}/map", contract.LATCHED_QOS)
        for agent in ("agent_0", "agent_1"):
            driver.create_publisher(PoseStamped, f"{ns}/{agent}/pose", contract.SENSOR_QOS)
            driver.create_publisher(RadiationReading, f"{ns}/{agent}/radiation", contract.SENSOR_QOS)
        driver.create_publisher(AgentMove, f"{ns}/agent_0/move", contract.RELIABLE_QOS)
        only_agent_1 = [f"{ns}/agent_1/move"]
        assert spin_until(executor, lambda: recorder.hold.silent(recorder._subs) == only_agent_1, 60.0)
        spin_until(executor, lambda: False, 0.5)  # the status publisher is discovered by now: still held
        assert f"{ns}/episode" not in recorder.subscribed and recorder.held is not None
        driver.create_publisher(AgentMove, f"{ns}/agent_1/move", contract.RELIABLE_QOS)
        assert spin_until(executor, lambda: recorder.hold.silent(recorder._subs) == [], 60.0)
        heard = time.monotonic()
        assert spin_until(executor, lambda: f"{ns}/episode" in recorder.subscribed, 60.0)
        assert time.monotonic() - heard >= HOLD_SETTLE_S - 0.1  # the writers' half of discovery

        # A recorder whose team never comes subscribes after hold_status_s all the same (timed
        # from before it is made: its hold starts when it is).
        start = time.monotonic()
        lonely = make_recorder_node("/hold_nobody", agents=1, discover_every_s=0.05,
                                    node_name="lonely_recorder", hold_status_s=1.0)
        nodes.append(lonely)
        executor.add_node(lonely)
        assert spin_until(executor, lambda: "/hold_nobody/episode" in lonely.subscribed, 60.0)
        assert time.monotonic() - start >= 1.0
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
