"""A lost UAV, idempotent moves, diagnostics a monitor can use, and robustness
(one map or one status must not freeze a team), with agent processes.

- The simulator and three ``medc-agent`` processes: every node's heartbeat comes at ~1 Hz; a hostile
  map (far-away origin, new map_load_time), a hostile status (step 10^9 with future-stamped poses
  and readings, the driver's own session) and a second driver's status are held and reported while
  the team keeps stepping; a move from another sender for agent_1 is reported as a duplicate agent
  id; a killed agent leaves a team that goes on finishing episodes.
- The documented driver (tests/ros/contract_driver.py, no simulator code) and the shipped team as
  three processes: a re-sent status yields a re-sent move that the driver executes once; a second
  process claiming agent_1 is detected; a UAV that is lost mid-episode (its pose and reading stop,
  its agent process is killed) leaves a team that finishes the episode.
"""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_helpers import DiagnosticsListener, run_contract_driver, start_node_process, stop_node_processes

HERE = Path(__file__).resolve().parent
TEAM = HERE.parents[1] / "models" / "team" / "A3W2.safetensors"
BIN = Path(sys.executable).parent


def _agent(i: int, policy: Path, log: Path, *extra: str) -> subprocess.Popen:
    return start_node_process([str(BIN / "medc-agent"), "--ros-args", "-p", f"agent_id:=agent_{i}",
                               "-p", f"policy:={policy}", *extra], log)


class Listener(DiagnosticsListener):
    """Records /diagnostics and the team's statuses, estimates and declarations; the tests publish
    hostile messages from its node."""

    def __init__(self) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from medc_common import contract
        from medc_interfaces.msg import EpisodeStatus, SourceDeclaration

        super().__init__("liveness_listener")
        self.statuses: list = []
        self.node.create_subscription(EpisodeStatus, contract.status_topic("/medc"), self.statuses.append,
                                      contract.RELIABLE_QOS)
        #: The team's source estimates and declarations (published by agent_0).
        self.estimates: list = []
        self.declarations: list = []
        self.estimate_sub = self.node.create_subscription(
            PoseWithCovarianceStamped, contract.estimate_topic("/medc"), self.estimates.append,
            contract.ESTIMATE_QOS)
        self.declaration_sub = self.node.create_subscription(
            SourceDeclaration, contract.declaration_topic("/medc"), self.declarations.append,
            contract.RELIABLE_QOS)

    def own(self, session: str) -> list:
        return [s for s in self.statuses if s.session == session]


def _assert_map_faults_clear(listen: Listener, names: tuple[str, ...], procs: list) -> None:
    """The fault of a foreign map clears: every node's ``map`` condition and, with it, every node's
    heartbeat are OK again once the team has gone on past the map."""
    from diagnostic_msgs.msg import DiagnosticStatus

    def latest_level(name: str):
        return next((s.level for _, s in reversed(listen.diagnostics) if s.name == name), None)

    def all_ok() -> bool:
        return all(latest_level(c) == DiagnosticStatus.OK for c in [*(f"{n}: map" for n in names), *names])

    assert listen.spin(60, all_ok, procs), {
        n: [(s.name, s.level, s.message[:80]) for _, s in listen.diagnostics[-200:]
            if s.name.startswith(n) and s.level != DiagnosticStatus.OK][-3:] for n in names}


@pytest.mark.timing
@pytest.mark.ros
def test_the_team_survives_hostile_messages_and_a_killed_agent(rclpy_context, bundles, tmp_path):
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PoseStamped
    from medc_common import contract
    from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading
    from nav_msgs.msg import OccupancyGrid

    listen = Listener()
    node = listen.node
    ns = "/medc"
    procs: list[subprocess.Popen] = []
    logs = {name: tmp_path / f"{name}.log" for name in ("sim", "agent_0", "agent_1", "agent_2")}
    try:
        procs.append(start_node_process(
            [str(BIN / "medc-sim"), "--ros-args", "-p", "agents:=3", "-p", "walls:=1", "-p", "grid:=10",
             "-p", "max_steps:=20", "-p", "seed:=3", "-p", "rate_hz:=20.0", "-p", "move_timeout_s:=1.0",
             "-p", "wait_for_subscribers:=3"], logs["sim"]))
        for i in range(3):
            procs.append(_agent(i, bundles["a"], logs[f"agent_{i}"], "-p", "agents:=3"))
        assert listen.spin(60, lambda: len(listen.statuses) >= 5, procs), "the team did not start"
        session = listen.statuses[-1].session
        assert session

        # A heartbeat per node every second: the summary status named after the node, timed by its
        # own stamps (when the node published it), so this listener's pace does not count. Eight
        # beats of a 1 s timer span 7 s; a node whose executor stalls delays the beats due meanwhile
        # and then runs them back to back, so allow 2.5 s of that: a 2 Hz heartbeat (3.5 s) still
        # fails. No gap may be so long that a monitor marking a node stale after a few seconds would.
        t0 = time.time()
        names = ("medc_sim", "medc_agent_0", "medc_agent_1", "medc_agent_2")
        assert listen.spin(90, lambda: all(len(listen.heartbeats(n, t0)) >= 8 for n in names), procs), \
            {n: listen.heartbeats(n, t0) for n in names}
        for name in names:
            beats = listen.heartbeats(name, t0)[:8]
            gaps = [round(b - a, 2) for a, b in itertools.pairwise(beats)]
            assert beats[-1] - beats[0] >= 4.5 and max(gaps) < 5.0, (name, gaps)

        def steps_after(since_count: int) -> int:
            return len([s for s in listen.own(session)[since_count:] if not s.done])

        # One valid map far away with a new map_load_time.
        map_pub = node.create_publisher(OccupancyGrid, contract.map_topic(ns), contract.LATCHED_QOS)
        hostile = OccupancyGrid()
        hostile.header.frame_id = "map"
        hostile.header.stamp = hostile.info.map_load_time = Time(sec=int(time.time()) + 5)
        hostile.info.resolution, hostile.info.width, hostile.info.height = 1.0, 10, 10
        hostile.info.origin.position.x = hostile.info.origin.position.y = 1000.0
        hostile.info.origin.orientation.w = 1.0
        hostile.data = [0] * 100
        t_map, count = time.monotonic(), len(listen.own(session))
        map_pub.publish(hostile)  # latched: every node gets it once it matches this publisher
        assert listen.spin(60, lambda: steps_after(count) >= 20, procs), "the team froze after one map"
        assert listen.spin(60, lambda: len(listen.warnings(t_map, "holds none of the team's")) >= 3, procs)
        assert listen.spin(60, lambda: listen.warnings(t_map, "did not publish", "medc_sim: map"), procs)
        _assert_map_faults_clear(listen, names, procs)

        # Future-stamped poses and readings and one status with step 10^9, in the
        # driver's own session, episode and map.
        pose_pubs = [node.create_publisher(PoseStamped, contract.pose_topic(ns, a), contract.SENSOR_QOS)
                     for a in contract.agent_ids(3)]
        read_pubs = [node.create_publisher(RadiationReading, contract.radiation_topic(ns, a),
                                           contract.SENSOR_QOS) for a in contract.agent_ids(3)]
        status_pub = node.create_publisher(EpisodeStatus, contract.status_topic(ns), contract.RELIABLE_QOS)
        # A status is volatile: sent before a reader matched, it never reaches it. Every status
        # reader of the graph (the three agents, the simulator's own watch, this listener) first.
        assert listen.spin(60, lambda: status_pub.get_subscription_count() >= 5, procs), \
            status_pub.get_subscription_count()
        for pub in (*pose_pubs, *read_pubs):  # the three agents
            assert listen.spin(60, lambda p=pub: p.get_subscription_count() >= 3, procs), pub.topic_name

        def latest_step():
            """The team's latest step as heard here (not an episode's end: that episode is over)."""
            return next(s for s in reversed(listen.own(session)) if not s.done)

        def send_hostile(current) -> None:
            future = Time(sec=int(time.time()) + 3600)
            for k, a in enumerate(contract.agent_ids(3)):
                pose = PoseStamped()
                pose.header.frame_id, pose.header.stamp = "map", future
                pose.pose.position.x, pose.pose.position.y = 0.5 + k, 0.5
                pose.pose.orientation.w = 1.0
                pose_pubs[k].publish(pose)
                read_pubs[k].publish(RadiationReading(header=pose.header, agent_id=a, value=5.0))
            bogus = EpisodeStatus(episode=current.episode, step=10**9, map_stamp=current.map_stamp,
                                  agent_ids=list(current.agent_ids), session=session)
            bogus.header.frame_id, bogus.header.stamp = "map", future
            status_pub.publish(bogus)

        # Episodes last at most 20 steps at 20 Hz: on a loaded machine the latest status heard here
        # may already be of an episode the agents have left. A status naming an earlier episode is
        # a driver restart to them (docs/ros-reference.md, "Episodes and restarts": they say so, "went
        # back ... step 1000000000", and follow it), not a jump within the episode: then the test
        # sends it again for the episode then in play. Every status that is neither reported as
        # a jump nor taken as a restart fails the test.
        def jumped(since: float) -> list:
            return listen.warnings(since, "jumps ahead")

        def restarted(since: float) -> set[str]:
            return {s.hardware_id for s in listen.warnings(since, "went back", ": team step")
                    if "1000000000" in s.message}

        held: list = []
        for _attempt in range(5):
            current = latest_step()
            t_status, count = time.monotonic(), len(listen.own(session))
            send_hostile(current)
            listen.spin(60, lambda t=t_status: jumped(t) or len(restarted(t)) == 3, procs)
            listen.spin(0.5, lambda t=t_status: jumped(t), procs)  # the others' reports, had some restarted
            held = jumped(t_status)
            if held:
                break
            assert restarted(t_status), (f"the hostile status (episode {current.episode} step 10^9) was "
                                         "neither reported as a jump nor followed as a restart")
            assert listen.spin(60, lambda c=count: steps_after(c) >= 20, procs), "froze after a restart"
        assert held, "the hostile status was not reported"
        assert all("1000000000" in s.message for s in held)
        assert listen.spin(60, lambda: steps_after(count) >= 20, procs), "the team froze after one status"

        # A second graph: a status of another session on the same namespace.
        other = EpisodeStatus(episode=0, step=0, map_stamp=current.map_stamp,
                              agent_ids=list(current.agent_ids), session="f00dfeedf00dfeed")
        other.header.frame_id, other.header.stamp = "map", Time(sec=int(time.time()))
        t_other, count = time.monotonic(), len(listen.own(session))
        status_pub.publish(other)
        assert listen.spin(60, lambda: steps_after(count) >= 10, procs)
        assert listen.spin(60, lambda: listen.warnings(t_other, "second graph", "medc_sim: graph"), procs)
        assert listen.spin(60, lambda: len({s.hardware_id for s in listen.warnings(t_other, "second")
                                            if s.hardware_id.startswith("agent_")}) == 3, procs)

        # A second process claiming agent_1: a move from another sender for the step in play.
        move_pub = node.create_publisher(AgentMove, contract.move_topic(ns, "agent_1"), contract.RELIABLE_QOS)
        # The simulator, agent_1 itself and its teammates (every agent follows every teammate's moves).
        assert listen.spin(60, lambda: move_pub.get_subscription_count() >= 3, procs), \
            move_pub.get_subscription_count()
        t_dup = time.monotonic()
        # The simulator tells a duplicate only for the step in play or the one just closed: a move
        # for a step heard here may be older than that on a loaded machine (then it is a foreign
        # move); send one for the latest step heard until the duplicate is reported (at least 3).
        duplicate = lambda: listen.warnings(t_dup, "duplicate agent id: agent_1", "medc_sim: moves")  # noqa: E731
        deadline = time.monotonic() + 60
        sent = 0
        while sent < 3 or (not duplicate() and time.monotonic() < deadline):
            now = latest_step()
            move_pub.publish(AgentMove(agent_id="agent_1", episode=now.episode, step=now.step, action=0,
                                       sender="0123456789abcdef"))
            sent += 1
            listen.spin(0.3, procs=procs)
        assert listen.spin(60, duplicate, procs), listen.warnings(t_dup, "agent_1", "medc_sim: moves")

        # Kill agent_2 mid-episode: the simulator reports the stall with its reason, takes agent_2
        # out after move_timeout_s (1 s here) and the two others go on finishing episodes.
        episodes_before = len([s for s in listen.own(session) if s.done])
        t_kill = time.monotonic()
        procs[3].send_signal(signal.SIGKILL)
        procs[3].wait(10)
        alive = procs[:3]
        assert listen.spin(90, lambda: len([s for s in listen.own(session) if s.done]) >= episodes_before + 2,
                           alive), "the team stopped after losing agent_2"
        assert listen.spin(60, lambda: listen.warnings(t_kill, "agent_2 lost", "medc_sim: team"), alive)
    finally:
        stop_node_processes(procs)
        listen.close()
    texts = {k: p.read_text() for k, p in logs.items()}
    assert not any("Traceback" in t for t in texts.values()), {k: t[-2000:] for k, t in texts.items()}
    # Each loss is logged once, each return once (a slow start may count as one loss and return).
    sim_log = texts["sim"]
    assert sim_log.count("agent_2 lost") == sim_log.count("agent_2 moved again") + 1, sim_log[-3000:]
    assert "duplicate agent id" in texts["sim"] and "two processes claim agent_1" in texts["sim"]


def node_publishers(listen: Listener, topic: str) -> int:
    return listen.node.count_publishers(topic)


def _run_driver(listen: Listener, name: str, tmp_path: Path, *extra: str, on_step=None):
    out, summary = tmp_path / f"{name}.jsonl", tmp_path / f"{name}.summary.json"

    def poll() -> None:
        if on_step is not None and out.exists():
            on_step(len(out.read_text().splitlines()))

    text = run_contract_driver(listen, ["--out", str(out), "--summary", str(summary), *extra], timeout_s=180,
                               on_poll=poll)
    steps = [json.loads(line) for line in out.read_text().splitlines()]
    return steps, json.loads(summary.read_text()), text


@pytest.mark.timing
@pytest.mark.ros
def test_a_documented_driver_executes_each_move_once_and_survives_a_lost_uav(rclpy_context, tmp_path):
    listen = Listener()
    logs = [tmp_path / f"agent_{i}.log" for i in range(3)]
    agents = [_agent(i, TEAM, logs[i]) for i in range(3)]
    duplicate = None
    try:
        # agent_0 publishes the team's estimate and declarations: this listener matches every
        # agent's publishers of them first (a volatile message sent before would never come).
        assert listen.spin(90, lambda: listen.declaration_sub.get_publisher_count() >= 3
                           and listen.estimate_sub.get_publisher_count() >= 3, agents)
        # Every status is re-sent: every agent re-sends its move; the driver executes each once.
        steps, summary, _ = _run_driver(listen, "resend", tmp_path, "--steps", "8", "--seed", "3",
                                        "--resend-always")
        assert len(steps) == 8
        assert all(s["received"] == [1, 1, 1] for s in steps), [s["received"] for s in steps]
        assert all(a is not None for s in steps for a in s["actions"])
        assert summary["resends_ignored"] >= 8, summary  # re-sent moves came and were recognised
        assert summary["moves_received"] == 24 + summary["resends_ignored"]
        assert summary["duplicates"] == []
        # The team's estimate, seen by a driver that imports no simulator code: every declaration
        # names the source of its episode (the driver's world: origin (-13, 4) m, 2 m cells), and
        # the estimate published with it lies in the declared cell.
        sources = {s["episode"]: tuple(s["source"]) for s in steps}
        listen.spin(60, lambda: len(listen.estimates) >= 4
                    and any(d.episode in sources for d in listen.declarations), agents)
        declared = [d for d in listen.declarations if d.episode in sources]
        assert declared, "the team declared no source in 8 steps"
        for d in declared:
            assert (d.cell_i, d.cell_j) == sources[d.episode], (d, sources)
            centre = (-13.0 + (d.cell_i + 0.5) * 2.0, 4.0 + (d.cell_j + 0.5) * 2.0)
            assert abs(d.position.x - centre[0]) < 1e-6 and abs(d.position.y - centre[1]) < 1e-6
        assert len(listen.estimates) >= 4, "the team's estimate is published every step"
        assert all(e.header.frame_id == "map" for e in listen.estimates)

        # A second process claims agent_1: the driver sees agent_1 answer from two senders.
        duplicate = _agent(1, TEAM, tmp_path / "duplicate.log", "-r", "__node:=medc_agent_1_again")
        team_topics = [f"/medc/agent_{k}/{kind}" for k in range(3) for kind in ("pose", "radiation")]
        assert listen.spin(90, lambda: node_publishers(listen, "/medc/agent_1/move") >= 2 and all(
            listen.node.count_subscribers(t) >= 4 for t in team_topics), agents)  # it listens to the team
        # Four agent processes: the driver's first step waits until all four hear it and it hears them.
        steps, summary, text = _run_driver(listen, "duplicate", tmp_path, "--steps", "8",
                                           "--seed", "4", "--settle-s", "3", "--processes", "4")
        assert len(steps) == 8 and all(s["received"] == [1, 1, 1] for s in steps)
        beats = [{kv.key: kv.value for kv in st.values} for _, st in listen.diagnostics
                 if st.name == "medc_agent_1_again"][-2:]
        assert summary["duplicates"], (summary, beats)
        assert {d[0] for d in summary["duplicates"]} == {"agent_1"}, summary
        assert "duplicate agent id: agent_1" in text
        # Each of the two processes sees the other's moves on its own topic and says so.
        claims = lambda: {s.name for s in listen.warnings(0, "two processes claim agent_1", ": moves")}  # noqa: E731
        assert listen.spin(60, lambda: len(claims()) == 2), claims()
        stop_node_processes([duplicate])

        # agent_2's UAV is lost at step 2 (its pose and reading stop) and its process is killed:
        # the two others take it out after lost_timeout_s and finish the episode.
        killed = {"done": False}

        def kill_at(n: int) -> None:
            if n >= 2 and not killed["done"]:  # step 2 is published: agent_2's UAV is silent
                agents[2].send_signal(signal.SIGKILL)
                killed["done"] = True

        t_lost = time.monotonic()
        steps, summary, _ = _run_driver(listen, "lost", tmp_path, "--steps", "40", "--seed", "5",
                                        "--max-steps", "15", "--episodes", "2", "--lose-agent", "2",
                                        "--lose-at-step", "2", on_step=kill_at)
        assert killed["done"]
        # Both episodes finished, at least one of them entirely without agent_2.
        assert len(summary["episodes"]) == 2 and len(steps) > 2, summary
        assert all(s["actions"][0] is not None and s["actions"][1] is not None for s in steps)
        assert all(s["actions"][2] is None for s in steps[2:])
        reported = lambda: {s.hardware_id for s in listen.warnings(t_lost, "agent_2 lost")}  # noqa: E731
        listen.spin(60, lambda: reported() >= {"agent_0", "agent_1"})
        lost = listen.warnings(t_lost, "agent_2 lost")
        assert {s.hardware_id for s in lost} == {"agent_0", "agent_1"}, [s.message for s in lost]
    finally:
        stop_node_processes(agents + ([duplicate] if duplicate is not None else []))
        listen.close()
    for i in (0, 1):
        text = logs[i].read_text()
        assert "Traceback" not in text
        assert text.count("agent_2 lost") == 1, text[-3000:]
