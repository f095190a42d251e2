"""The one protection that works with the pinned wheels: a mission in a network namespace of its
own with a private /dev/shm (docs/security.md, "How to run secured"). A node outside it, on the
same ROS_DOMAIN_ID and namespace, neither sees the team nor reaches it: its forged statuses,
poses, readings, moves and declarations match no reader, it reads nothing, and every episode of the
team finds the source; a node inside the mission's namespaces sees the team (the control that the
outside view is not empty by mistake)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from ros_helpers import stop_launcher

SCENARIO = {"agents": 3, "walls": 2, "grid": 10, "max_steps": 30, "seed": 5}
EPISODES = 3
#: What ends an episode besides max_steps: the source reached or the team's declaration, so that the
#: driver reads declarations (under end_on: source nothing does) and a forged one would end an episode.
END_ON = "either"
#: A namespace of its own, so that other graphs on this domain (other tests) cannot be taken for the team.
NS = f"/isolated_{os.getpid()}"

#: The nanoseconds of every forged message's stamp: how the intruder tells its own messages apart.
FORGED_NANOSEC = 424242

#: The recipe of docs/security.md: loopback up, a private /dev/shm, then the launcher.
ISOLATE = ["unshare", "--net", "--mount", "--propagation", "private", "sh", "-c",
           'ip link set lo up && mount -t tmpfs -o mode=1777 tmpfs /dev/shm && exec "$@"', "isolate"]

#: Joins the mission's namespaces (nsenter) and reads its episode status and results, as a tool the
#: launcher waits for (``--listeners 1``) would: the team's first step waits until it is matched, so
#: it cannot miss a team that plays its episodes quickly. Exits 0 once the team's status has a
#: publisher and its declaration topic a reader (the driver's, under end_on: either); it stays
#: until told to go (stdin closed), so the finished simulator finds its results reader there.
INSIDER = """
import sys, time, rclpy
from medc_common import contract
from medc_interfaces.msg import EpisodeStatus
rclpy.init()
node = rclpy.create_node("insider")
ns = sys.argv[2]
node.create_subscription(EpisodeStatus, contract.status_topic(ns), lambda m: None, contract.RELIABLE_QOS)
node.create_subscription(EpisodeStatus, contract.results_topic(ns), lambda m: None, contract.RESULTS_QOS)
deadline = time.monotonic() + float(sys.argv[1])
seen = False
while time.monotonic() < deadline and not seen:
    seen = (node.count_publishers(contract.status_topic(ns)) > 0
            and node.count_subscribers(contract.declaration_topic(ns)) > 0)
    rclpy.spin_once(node, timeout_sec=0.2)
print("SEES THE TEAM" if seen else "SAW NOTHING", flush=True)
sys.stdin.read()
sys.exit(0 if seen else 1)
"""


def _can_isolate() -> bool:
    if not (shutil.which("unshare") and shutil.which("ip") and shutil.which("nsenter")):
        return False
    try:
        out = subprocess.run([*ISOLATE, "true"], capture_output=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0




class Intruder:
    """A node outside the mission: publishes a forged message of every kind the team accepts
    (status, pose, reading, move, declaration, map, policy) and listens to every team topic."""

    def __init__(self, node, agents: list[str]):
        from geometry_msgs.msg import PoseStamped
        from medc_common import contract
        from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading, SourceDeclaration
        from nav_msgs.msg import OccupancyGrid
        from std_msgs.msg import String

        self.node, self.agents, self.heard = node, agents, []
        sensor, reliable, latched = contract.SENSOR_QOS, contract.RELIABLE_QOS, contract.LATCHED_QOS
        self.pubs = {
            "status": node.create_publisher(EpisodeStatus, contract.status_topic(NS), reliable),
            "declaration": node.create_publisher(SourceDeclaration, contract.declaration_topic(NS), reliable),
            "map": node.create_publisher(OccupancyGrid, contract.map_topic(NS), latched),
            "team_policy": node.create_publisher(String, contract.team_policy_topic(NS), latched),
        }
        for a in agents:
            self.pubs[f"pose {a}"] = node.create_publisher(PoseStamped, contract.pose_topic(NS, a), sensor)
            self.pubs[f"reading {a}"] = node.create_publisher(
                RadiationReading, contract.radiation_topic(NS, a), sensor)
            self.pubs[f"move {a}"] = node.create_publisher(AgentMove, contract.move_topic(NS, a), reliable)
        listen = [(EpisodeStatus, contract.status_topic(NS), reliable),
                  (EpisodeStatus, contract.results_topic(NS), contract.RESULTS_QOS),
                  (SourceDeclaration, contract.declaration_topic(NS), reliable),
                  (OccupancyGrid, contract.map_topic(NS), contract.MAP_READER_QOS)]
        for a in agents:
            listen += [(PoseStamped, contract.pose_topic(NS, a), sensor),
                       (RadiationReading, contract.radiation_topic(NS, a), sensor),
                       (AgentMove, contract.move_topic(NS, a), reliable)]
        self.topics = [t for _, t, _ in listen]
        for msg_type, topic, qos in listen:
            node.create_subscription(msg_type, topic, lambda m, t=topic: self.hear(t, m), qos)
        self.types = (AgentMove, EpisodeStatus, RadiationReading, SourceDeclaration, PoseStamped, String)
        self.step = 0

    def hear(self, topic: str, msg) -> None:
        if msg.header.stamp.nanosec != FORGED_NANOSEC:  # not one of its own
            self.heard.append(topic)

    def forge(self) -> None:
        AgentMove, EpisodeStatus, RadiationReading, SourceDeclaration, PoseStamped, String = self.types
        stamp = self.node.get_clock().now().to_msg()
        stamp.nanosec = FORGED_NANOSEC
        self.step += 1
        status = EpisodeStatus(episode=0, step=10**9 + self.step, session="intruder", agent_ids=self.agents)
        status.header.stamp = stamp
        self.pubs["status"].publish(status)
        self.pubs["team_policy"].publish(String(data="/etc/passwd"))
        for a in self.agents:
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = stamp, "map"
            self.pubs[f"pose {a}"].publish(pose)
            reading = RadiationReading(agent_id=a, value=1e6, variance=0.0)
            reading.header.stamp = stamp
            self.pubs[f"reading {a}"].publish(reading)
            for episode in range(EPISODES):
                for step in range(SCENARIO["max_steps"]):
                    move = AgentMove(agent_id=a, episode=episode, step=step, sender="intruder", action=0)
                    move.header.stamp = stamp
                    self.pubs[f"move {a}"].publish(move)
                    if a == "agent_0":  # a declaration of cell (0, 0) for every step of every episode
                        declaration = SourceDeclaration(agent_id=a, episode=episode, step=step, cell_i=0,
                                                        cell_j=0, mass=1.0)
                        declaration.header.stamp = stamp
                        self.pubs["declaration"].publish(declaration)

    # The intruder's own readers and writers on these topics are not counted (it reads what it forges).
    def matched_readers(self) -> dict[str, int]:
        counts = {k: p.get_subscription_count() - (p.topic_name in self.topics) for k, p in self.pubs.items()}
        return {k: n for k, n in counts.items() if n}

    def team_publishers(self) -> dict[str, int]:
        own = {p.topic_name for p in self.pubs.values()}
        counts = {t: self.node.count_publishers(t) - (t in own) for t in self.topics}
        return {t: n for t, n in counts.items() if n}


@pytest.mark.ros
@pytest.mark.timing
@pytest.mark.slow
def test_an_outside_node_neither_reaches_nor_reads_an_isolated_team(tmp_path, rclpy_context):
    import rclpy
    from medc_common import contract
    from rclpy.executors import SingleThreadedExecutor

    if not _can_isolate():
        pytest.skip("needs unshare --net --mount (root or user namespaces), ip and nsenter")
    config = tmp_path / "launch.yaml"
    config.write_text(json.dumps({**SCENARIO, "sensing": "paper-simple", "namespace": NS, "end_on": END_ON}))
    node = rclpy.create_node("intruder")
    intruder = Intruder(node, contract.agent_ids(SCENARIO["agents"]))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.create_timer(0.2, intruder.forge)

    err = tmp_path / "launch.err"
    launcher = [sys.executable, "-m", "medc_bringup.launcher", "--config", str(config), "--policy", "greedy",
                "--episodes", str(EPISODES), "--timeout", "240", "--listeners", "1"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with err.open("w") as log:
        proc = subprocess.Popen([*ISOLATE, *launcher], stdout=subprocess.PIPE, stderr=log, text=True,
                                env=env, start_new_session=True)
    insider = None
    insider_log = tmp_path / "insider.log"
    seen_readers: dict[str, int] = {}
    seen_publishers: dict[str, int] = {}
    try:
        # The control: a node that joins the mission's namespaces (once the launcher is in them) sees it.
        own_net, deadline = os.readlink("/proc/self/ns/net"), time.monotonic() + 60
        while os.readlink(f"/proc/{proc.pid}/ns/net") == own_net:
            assert proc.poll() is None and time.monotonic() < deadline, err.read_text()[-3000:]
            executor.spin_once(timeout_sec=0.05)
        with insider_log.open("w") as log:
            join = ["nsenter", "-t", str(proc.pid), "--net", "--mount"]
            insider = subprocess.Popen([*join, sys.executable, "-c", INSIDER, "240", NS],
                                       stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT, text=True,
                                       env=env, start_new_session=True)
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            seen_readers.update(intruder.matched_readers())
            seen_publishers.update(intruder.team_publishers())
        assert proc.poll() is not None, "the isolated team did not finish its episodes"
        insider.stdin.close()  # it may go once it has seen the team
        insider.wait(270)
    finally:
        if insider is not None and insider.poll() is None:
            os.killpg(insider.pid, signal.SIGKILL)
            insider.wait()
        if proc.poll() is None:
            stop_launcher(proc)
        executor.shutdown()
        node.destroy_node()
    out, insider_out = proc.stdout.read(), insider_log.read_text()
    assert proc.returncode == 0, err.read_text()[-3000:]
    assert insider.returncode == 0 and "SEES THE TEAM" in insider_out, insider_out
    assert intruder.step > 5  # it kept forging while the team played
    assert seen_readers == {}, f"the team read the intruder's topics: {seen_readers}"
    assert seen_publishers == {}, f"the intruder saw the team's publishers: {seen_publishers}"
    assert intruder.heard == [], f"the intruder read the team's messages on {sorted(set(intruder.heard))}"
    # Every episode found the source (a forged declaration of cell (0, 0) would have ended one).
    result = json.loads(out.strip().splitlines()[-1])
    assert result["episodes"] == EPISODES and all(result["successes"]), result
    assert "intruder" not in err.read_text()


def test_listeners_must_not_be_negative(capsys):
    from medc_bringup.launcher import main

    with pytest.raises(SystemExit) as exc:
        main(["--policy", "greedy", "--listeners", "-1", "--episodes", "1"])
    assert exc.value.code == 2
    assert "--listeners must be >= 0, got -1" in capsys.readouterr().err
