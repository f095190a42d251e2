"""medc-record: record a running MEDC graph to MCAP and/or serve it live to Foxglove.

    medc-record -o mission.mcap                   # every topic under /medc, until Ctrl-C
    medc-record -o mission.mcap --foxglove        # and a live view on ws://127.0.0.1:8765
    medc-record --foxglove 8766 --namespace /team2
    medc-record --foxglove --foxglove-origin https://app.foxglove.dev   # serve the Foxglove web app too
    medc-record -o mission.mcap --overwrite       # replace mission.mcap if it exists

The recorder finds the topics under the namespace (and ``/diagnostics``) as they appear, so
topics added later (the team's estimate, for one) are recorded too. The file is rosbag2's MCAP
layout (profile ``ros2``, ``ros2msg`` schemas from the installed ``.msg`` files, CDR messages):
``ros2 bag info``, ``rosbags``, ``mcap_ros2`` and Foxglove read it. Ctrl-C (or SIGTERM) finishes
the file; the last line on stdout is a JSON summary (topics, message counts, bytes, the time the
recorder spent per message). The file is checked before anything is recorded (a folder, a device,
a name too long, a folder it cannot write, or an existing file or link without ``--overwrite``:
refused in one line, status 2) and written under a fresh temporary name beside it
(``.NAME.XXXXXXXX.tmp``, where a killed recorder leaves what it had), moved into place when the
file is finished: never through a link. A recorder never holds the simulator back or stands in for an agent:
the simulator starts when every agent's own move publisher is there.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from rclpy.node import Node
from rclpy.serialization import deserialize_message

from medc_bringup.live_view import DEFAULT_MAX_CLIENTS

#: Topics outside the namespace that belong to a MEDC graph.
GLOBAL_TOPICS = ("/diagnostics",)
#: Seconds the recorder holds its episode-status subscription back waiting for the agents (the
#: simulator's start gate waits as long: medc_sim.start_gate.START_WAIT_S).
HOLD_STATUS_S = 30.0
#: Seconds every needed subscription must have had its publisher before the recorder takes the status
#: (StatusHold): this reader matching a writer is one half of DDS discovery; the writer matches the
#: reader (and only then sends to it) when the other half reaches it, as a rule a moment later.
HOLD_SETTLE_S = 0.5


def _ns(namespace: str) -> str:
    ns = "/" + namespace.strip("/")
    return "" if ns == "/" else ns


def known_topics(namespace: str, agents: int = 0) -> dict[str, tuple[str, object]]:
    """The contract's topics (docs/ros-reference.md) with their types and QoS, subscribed before they are
    discovered so that nothing published early is lost; ``agents``: also those of agent_0..N-1."""
    from medc_common import contract

    ns = namespace
    topics = {
        contract.map_topic(ns): ("nav_msgs/msg/OccupancyGrid", contract.LATCHED_QOS),
        contract.status_topic(ns): ("medc_interfaces/msg/EpisodeStatus", contract.RELIABLE_QOS),
        contract.results_topic(ns): ("medc_interfaces/msg/EpisodeStatus", contract.RESULTS_QOS),
        contract.team_policy_topic(ns): ("std_msgs/msg/String", contract.LATCHED_QOS),
    }
    for a in contract.agent_ids(agents) if agents > 0 else []:
        topics[contract.pose_topic(ns, a)] = ("geometry_msgs/msg/PoseStamped", contract.SENSOR_QOS)
        topics[contract.radiation_topic(ns, a)] = (
            "medc_interfaces/msg/RadiationReading", contract.SENSOR_QOS)
        topics[contract.move_topic(ns, a)] = ("medc_interfaces/msg/AgentMove", contract.RELIABLE_QOS)
        topics[contract.policy_topic(ns, a)] = ("std_msgs/msg/String", contract.LATCHED_QOS)
    return topics


def live_topics(namespace: str, agents: int = 0) -> list[tuple[str, str, str, bool]]:
    """The topics the live view serves from its start, before any client connects (see
    :class:`medc_bringup.live_view.LiveView`): :func:`known_topics`, the team estimator's and
    ``/diagnostics``, as ``(topic, type name, ros2msg definition, latched)``."""
    from medc_common import contract

    from medc_bringup.recording import message_definition

    topics = dict(known_topics(namespace, agents))
    topics[contract.estimate_topic(namespace)] = ("geometry_msgs/msg/PoseWithCovarianceStamped",
                                                  contract.ESTIMATE_QOS)
    topics[contract.posterior_topic(namespace)] = ("nav_msgs/msg/OccupancyGrid", contract.LATCHED_QOS)
    topics[contract.declaration_topic(namespace)] = ("medc_interfaces/msg/SourceDeclaration",
                                                     contract.RELIABLE_QOS)
    topics[contract.DIAGNOSTICS_TOPIC] = ("diagnostic_msgs/msg/DiagnosticArray", contract.DIAGNOSTICS_QOS)
    return [(topic, type_name, message_definition(type_name), _is_latched(qos))
            for topic, (type_name, qos) in topics.items()]


def _is_latched(qos) -> bool:
    """Whether a subscription QoS is transient local (the topic keeps its last message)."""
    from rclpy.qos import DurabilityPolicy

    return qos.durability == DurabilityPolicy.TRANSIENT_LOCAL


def qos_for_publishers(infos):
    """A subscription QoS that matches every publisher in ``infos`` (rclpy TopicEndpointInfo):
    reliable only if all are, transient local only if all are; keep last 100."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSProfile(
        depth=100,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class StatusHold:
    """When the recorder knows the team (``agents`` > 0), it subscribes to the episode status only
    once each of its subscriptions to the map and to every agent's pose, reading and move topics is
    matched with a publisher. The simulator's start gate counts the recorder among the status
    listeners (medc-launch --record), so the first step then waits until the recorder hears every
    agent: a reliable, volatile move sent before the writer matched the recorder would never reach
    it. The publishers must have been there ``settle_s`` (HOLD_SETTLE_S). After ``timeout_s`` it
    subscribes anyway (the simulator starts anyway after as long)."""

    def __init__(self, namespace: str, agents: int, timeout_s: float = HOLD_STATUS_S,
                 settle_s: float = HOLD_SETTLE_S) -> None:
        from medc_common import contract

        self.topic = contract.status_topic(namespace) if agents > 0 else None
        self.needed = [contract.map_topic(namespace)] + [
            topic(namespace, a) for a in contract.agent_ids(agents)
            for topic in (contract.pose_topic, contract.radiation_topic, contract.move_topic)
        ] if agents > 0 else []
        self.deadline = time.monotonic() + timeout_s
        self.settle_s = settle_s
        self._heard_at: float | None = None

    def silent(self, subscriptions: dict) -> list[str]:
        """The needed topics whose subscription (in ``subscriptions``, by topic) has no publisher."""
        return [t for t in self.needed
                if t not in subscriptions or subscriptions[t].get_publisher_count() == 0]

    def due(self, subscriptions: dict) -> bool:
        """Whether to subscribe to the status now: every needed topic has had a publisher for
        ``settle_s``, or the hold expired."""
        now = time.monotonic()
        if self.silent(subscriptions):
            self._heard_at = None
        elif self._heard_at is None:
            self._heard_at = now
        return now > self.deadline or (self._heard_at is not None and now - self._heard_at >= self.settle_s)


class RecorderNode(Node):
    """Subscribes to the graph's topics as they appear (see the module docstring and
    :func:`make_recorder_node`)."""

    def __init__(self, namespace: str, recording=None, live=None, agents: int = 0,
                 discover_every_s: float = 0.2, node_name: str = "medc_recorder",
                 hold_status_s: float = HOLD_STATUS_S) -> None:
        from medc_common import contract

        # In the team's namespace (/team2/medc_recorder): two teams' recorders do not clash. The
        # topics it subscribes to are fully qualified.
        super().__init__(node_name, namespace=contract.check_namespace(namespace))
        self.ns = _ns(namespace)
        self._recording, self._live, self._hold_status_s = recording, live, hold_status_s
        self.subscribed: dict[str, str] = {}
        self.skipped: set[str] = set()
        self.messages = 0
        self.busy_s = 0.0
        self._subs: dict[str, object] = {}
        self.hold = StatusHold(namespace, agents, hold_status_s)
        topics = known_topics(namespace, agents)
        #: The status subscription held back (StatusHold); None once subscribed.
        self.held = (self.hold.topic, topics.pop(self.hold.topic)) if self.hold.topic else None
        for topic, (type_name, qos) in topics.items():
            self._subscribe(topic, type_name, qos)
        self._discover()
        self.create_timer(discover_every_s, self._discover)
        if live is not None:
            self.create_timer(0.5, live.tick)

    def _ours(self, topic: str) -> bool:
        return topic.startswith(self.ns + "/") or topic in GLOBAL_TOPICS

    def _release(self) -> None:
        """Subscribe to the held status topic once the team is heard (StatusHold)."""
        if not self.hold.due(self._subs):
            return
        silent = self.hold.silent(self._subs)
        if silent:
            self.get_logger().warning(f"no publisher on {', '.join(silent)} after {self._hold_status_s:g} s; "
                                      "recording the episode status anyway")
        topic, (type_name, qos) = self.held
        self.held = None
        self._subscribe(topic, type_name, qos)

    def _discover(self) -> None:
        if self.held is not None:
            self._release()
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subscribed or topic in self.skipped or not self._ours(topic) or not types:
                continue
            if self.held is not None and topic == self.held[0]:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # only subscribers so far: match the publishers once they appear
            self._subscribe(topic, types[0], qos_for_publishers(infos))

    def _subscribe(self, topic: str, type_name: str, qos) -> None:
        from medc_bringup.recording import message_class, message_definition

        try:
            cls = message_class(type_name)
            definition = message_definition(type_name)
        except ValueError as exc:
            self.skipped.add(topic)
            self.get_logger().warning(f"not recording {topic}: {exc}")
            return
        recording, live = self._recording, self._live
        if recording is not None:
            recording.add_topic(topic, type_name, qos)
        decode = None
        if live is not None:
            live.add_topic(topic, type_name, definition, latched=_is_latched(qos))
            if live.wants(topic, type_name):
                decode = cls
        self.subscribed[topic] = type_name
        self._subs[topic] = self.create_subscription(
            cls, topic, lambda data, t=topic, n=type_name, d=decode: self._on_message(t, n, d, data),
            qos, raw=True,
        )

    def _on_message(self, topic: str, type_name: str, decode, data: bytes) -> None:
        t0 = time.perf_counter()
        now = time.time_ns()
        recording, live = self._recording, self._live
        if recording is not None and not recording.closed and recording.failed is None:
            recording.write(topic, data, now)
            if recording.failed is not None:
                self.get_logger().error(f"the recording stopped: {recording.failed} (the live view, "
                                        "if any, goes on)")
        if live is not None:
            msg = deserialize_message(data, decode) if decode is not None else None
            live.on_message(topic, type_name, data, msg, now)
        self.messages += 1
        self.busy_s += time.perf_counter() - t0


def make_recorder_node(namespace: str, recording=None, live=None, agents: int = 0,
                       discover_every_s: float = 0.2, node_name: str = "medc_recorder",
                       hold_status_s: float = HOLD_STATUS_S):
    """A node that subscribes (raw CDR) to every MEDC topic and hands each message to
    ``recording`` (a :class:`medc_bringup.recording.McapRecording`) and ``live``
    (a :class:`medc_bringup.live_view.LiveView`); either may be None. With ``agents`` > 0 its
    status subscription waits for the team, ``hold_status_s`` at most (:class:`StatusHold`)."""
    return RecorderNode(namespace, recording, live, agents, discover_every_s, node_name, hold_status_s)


def start_recorder(cfg, record: str | None, foxglove: int | None, quiet: bool = False,
                   overwrite: bool = False, foxglove_clients: int | None = None,
                   foxglove_origins: tuple[str, ...] = ()):
    """For ``medc-launch --record/--foxglove``: start ``medc-record`` for ``cfg``'s team as its own
    process (own session: Ctrl-C reaches the launcher, which stops it last). None if neither is
    asked for. A relative ``record`` path is taken from the current directory; ``overwrite``
    replaces an existing file; ``foxglove_clients`` and ``foxglove_origins`` are medc-record's
    ``--foxglove-clients`` and ``--foxglove-origin``.

    Raises:
        ValueError: the record file cannot be written there (checked as ``medc-record -o`` checks
        it, before the mission), the reason said.
    """
    import os
    import subprocess

    from medc_common.ros_env import interfaces_env

    if record is None and foxglove is None:
        return None
    command = [sys.executable, "-m", "medc_bringup.recorder", "--namespace", cfg.namespace,
               "--agents", str(cfg.agents)]
    if record is not None:
        from medc_training.outfiles import check_output

        try:
            path = check_output(Path(record).expanduser(), overwrite)
        except ValueError as exc:
            raise ValueError(f"--record {clean_path(record)}: {exc}") from None
        command += ["--output", str(path)] + (["--overwrite"] if overwrite else [])
    if foxglove is not None:
        command += ["--foxglove", str(foxglove)]
        if foxglove_clients is not None:
            command += ["--foxglove-clients", str(foxglove_clients)]
        for origin in foxglove_origins:
            command += ["--foxglove-origin", origin]
    if quiet:
        command.append("--quiet")
    env = interfaces_env()
    env["PYTHONUNBUFFERED"] = "1"
    # The package may run from a source tree (PYTHONPATH) rather than an install: keep it importable.
    here = str(Path(__file__).resolve().parents[1])
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([here, *rest])
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, text=True, start_new_session=True)


def stop_recorder(process, grace_s: float = 15.0) -> dict | None:
    """SIGINT the recorder started by :func:`start_recorder`, wait for it to finish its file and
    return its JSON summary (None if it printed none; killed after ``grace_s``)."""
    import signal
    import subprocess

    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        out, _ = process.communicate(timeout=grace_s)
    except subprocess.TimeoutExpired:
        process.kill()
        out, _ = process.communicate()
    for line in reversed((out or "").splitlines()):
        try:
            return json.loads(line)
        except ValueError:
            continue
    return None


def clean_path(path: str) -> str:
    """``path`` for a one-line message: control characters escaped, at most 200 characters."""
    text = path.encode("unicode_escape", "backslashreplace").decode("ascii")
    return text if len(text) <= 200 else text[:200] + "..."


def open_recording(path: str, overwrite: bool = False, compression: str = "zstd"):
    """``(output path, its AtomicOutput, McapRecording)`` of ``medc-record -o PATH``, before the
    mission: the target is checked (:func:`medc_training.outfiles.check_output`: a folder, a
    device such as ``/dev/full``, a name too long, a missing or unwritable folder, or, unless
    ``overwrite``, an existing file or link are refused), the recording starts in a fresh temporary
    file beside it and its header is written through to the disk.

    Raises:
        ValueError: the reason (OutputError), the file unchanged.
    """
    from medc_training.outfiles import AtomicOutput, OutputError, check_output

    from medc_bringup.recording import McapRecording

    output = check_output(Path(path).expanduser(), overwrite)
    target = AtomicOutput(output, overwrite)
    try:
        recording = McapRecording(target.file, compression=compression)
        recording.flush()
        target.sync()
    except OSError as exc:
        target.discard()
        raise OutputError(f"cannot write {output}: {exc.strerror or exc}") from None
    except BaseException:
        target.discard()
        raise
    return output, target, recording


def finish_recording(recording, target) -> str | None:
    """Close ``recording`` and move its temporary file into place (``target``, an AtomicOutput);
    None, or what went wrong, in one line (a recording the disk refused is removed; one whose name
    was taken meanwhile is kept where the message says)."""
    from medc_training.outfiles import OutputError

    recording.close()
    if recording.failed is not None:
        target.discard()
        return f"the recording stopped: cannot write {target.target}: {recording.failed}"
    try:
        target.commit()
    except (OutputError, OSError) as exc:
        return str(exc)
    return None


def spin_then_drain(drain_s: float):
    """A ``run_node`` spin function: spin until stopped, then ``drain_s`` more seconds so that
    messages already on their way (the last episode's result) are still written."""
    def spin(node, executor) -> None:
        import rclpy
        from medc_common.executors import spin_once_alive, spin_until_shutdown

        spin_until_shutdown(node, executor)
        end = time.monotonic() + drain_s
        while rclpy.ok() and time.monotonic() < end and spin_once_alive(executor, 0.05):
            pass

    return spin


def build_parser() -> argparse.ArgumentParser:
    from medc_training.console import QUIET_HELP, HelpFormatter, epilog

    parser = argparse.ArgumentParser(
        prog="medc-record", description=__doc__.split("\n\n")[0],
        formatter_class=HelpFormatter, epilog=epilog(__doc__),
    )
    parser.add_argument("-o", "--output", help="MCAP file to write (rosbag2 layout); none = do not record")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the -o file if it exists (a link there is replaced, never written "
                             "through)")
    parser.add_argument("--namespace", default="/medc",
                        help="the team's namespace: every topic under it is recorded")
    parser.add_argument("--foxglove", nargs="?", type=int, const=8765, default=None, metavar="PORT",
                        help="also serve a live view to Foxglove on ws://127.0.0.1:PORT (0 = any free port)")
    parser.add_argument("--foxglove-clients", type=int, default=DEFAULT_MAX_CLIENTS, metavar="N",
                        help="connections the live view serves at once; one more is refused with a close "
                             "reason")
    parser.add_argument("--foxglove-origin", action="append", default=[], metavar="ORIGIN",
                        help="also serve web pages of this origin (e.g. https://app.foxglove.dev; repeat for "
                             "more): the live view refuses any page not served by this machine")
    parser.add_argument("--agents", type=int, default=0,
                        help="subscribe to agent_0..N-1's topics at once instead of when discovered")
    parser.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd",
                        help="MCAP chunk compression")
    parser.add_argument("--drain", type=float, default=0.5,
                        help="seconds to keep receiving after Ctrl-C before the file is closed")
    parser.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-record`` (see the module docstring)."""
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.output is None and args.foxglove is None:
        parser.error("nothing to do: give -o FILE.mcap, --foxglove [PORT], or both")
    if args.foxglove_clients < 1:
        parser.error(f"--foxglove-clients must be at least 1, got {args.foxglove_clients}")
    from medc_common.contract import check_namespace

    try:
        args.namespace = check_namespace(args.namespace)
    except ValueError as exc:
        parser.error(f"--namespace: {exc}")
    from medc_common.ros_env import require_interfaces

    require_interfaces()
    from medc_common.executors import run_node

    output = target = recording = None
    if args.output is not None:
        # Before the mission: the file is refused at once when it cannot be written there.
        try:
            output, target, recording = open_recording(args.output, args.overwrite, args.compression)
        except ValueError as exc:
            print(f"medc-record: {exc}", file=sys.stderr)
            return 2
    live = None
    holder: dict[str, object] = {}
    try:
        if args.foxglove is not None:
            from medc_bringup.live_view import LiveView

            try:
                live = LiveView(args.namespace, port=args.foxglove,
                                topics=live_topics(args.namespace, args.agents),
                                max_clients=args.foxglove_clients,
                                allowed_origins=tuple(args.foxglove_origin))
            except Exception as exc:  # the SDK raises its own error types for a busy port
                print(f"medc-record: cannot start the Foxglove server on 127.0.0.1:{args.foxglove}: {exc} "
                      "(pick another port with --foxglove PORT, or 0 for any free one)", file=sys.stderr)
                return 2
            if not args.quiet:
                print(f"medc-record: Foxglove live view on ws://127.0.0.1:{live.port} "
                      f"(scene: {live.scene_topic})", file=sys.stderr, flush=True)

        def make_node():
            node = make_recorder_node(args.namespace, recording, live, agents=args.agents)
            holder["node"] = node
            return node

        rc = run_node("medc-record", argv, make_node, spin=spin_then_drain(args.drain))
    finally:
        failed = None
        if recording is not None and "node" not in holder:  # no mission: nothing to keep
            recording.close()
            target.discard()
        elif recording is not None:
            failed = finish_recording(recording, target)
        if live is not None:
            live.close()
    if failed is not None:
        print(f"medc-record: {failed}", file=sys.stderr)
        rc = rc or 2
    node = holder.get("node")
    messages = getattr(node, "messages", 0)
    summary = {
        "output": str(output) if output is not None else None,
        "foxglove_port": live.port if live is not None else None,
        "topics": dict(sorted(recording.counts.items())) if recording is not None else sorted(
            getattr(node, "subscribed", {})),
        "messages": messages,
        "bytes": recording.bytes if recording is not None else 0,
        "file_bytes": (output.stat().st_size if output is not None and failed is None and output.exists()
                       else 0),
        "per_message_us": round(1e6 * getattr(node, "busy_s", 0.0) / messages, 2) if messages else None,
    }
    print(json.dumps(summary), flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
