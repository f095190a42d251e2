"""The Foxglove live view (medc-launch --foxglove): a WebSocket client speaking Foxglove's
protocol receives the 3D scene (walls, agents, tracks, readings) and the raw ROS topics."""

from __future__ import annotations

import base64
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _protobuf_class(schema_b64: str, name: str):
    """The message class of ``name`` from a base64 FileDescriptorSet (what Foxglove advertises)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def _connect(port: int, deadline: float):
    from websockets.sync.client import connect

    while True:
        try:
            # No keep-alive pings: a client that stops reading (done watching) is not dropped.
            return connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=2,
                           ping_interval=None)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


class _Client:
    """A Foxglove-protocol client: subscribes to each channel of ``wanted`` as advertised (a
    channel advertised again gets a new id and a new subscription), collects its data frames by
    topic (``got``); ``channels``: every advertised channel; ``errors``: the server's error
    statuses; ``unadvertised``: the channel ids the server withdrew."""

    def __init__(self, ws, wanted: set[str]) -> None:
        self.ws, self.wanted = ws, wanted
        self.channels: dict[str, dict] = {}
        self.got: dict[str, list[bytes]] = {}
        self.errors: list[str] = []
        self.unadvertised: list[int] = []
        self._subscribed: dict[int, str] = {}
        self._channel_ids: set[int] = set()

    def receive(self, timeout: float) -> None:
        """Handle one frame (if one comes within ``timeout``)."""
        try:
            frame = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return
        if isinstance(frame, str):
            op = json.loads(frame)
            if op["op"] == "advertise":
                new = []
                for c in op["channels"]:
                    self.channels[c["topic"]] = c
                    if c["topic"] in self.wanted and c["id"] not in self._channel_ids:
                        self._channel_ids.add(c["id"])
                        self._subscribed[len(self._subscribed) + 1] = c["topic"]
                        new.append({"id": len(self._subscribed), "channelId": c["id"]})
                if new:
                    self.ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif op["op"] == "unadvertise":
                self.unadvertised.extend(op["channelIds"])
            elif op["op"] == "status" and op.get("level") == 2:
                self.errors.append(op["message"])
            return
        assert frame[0] == 0x01  # message data
        (sub_id,) = struct.unpack_from("<I", frame, 1)
        self.got.setdefault(self._subscribed[sub_id], []).append(bytes(frame[13:]))


WANTED = {"/medc/scene", "/medc/episode", "/medc/agent_0/pose", "/medc/agent_1/radiation", "/medc/map"}


def _decoder(channel: dict):
    """The decoder of a ``ros2msg`` channel's CDR messages."""
    from mcap_ros2._dynamic import generate_dynamic

    return generate_dynamic(channel["schemaName"], channel["schema"])[channel["schemaName"]]


class _Viewer:
    """A client of the live view that watches until it has seen what a user looks for: the walls
    map, at least three messages of each other wanted topic, and a scene with an agent's track."""

    def __init__(self, port: int, deadline: float, until=lambda: True) -> None:
        self.client = _Client(_connect(port, deadline).__enter__(), WANTED)
        self.deadline = deadline
        self.until = until  # it watches on until this holds too
        self.SceneUpdate = None
        self.track_seen = False
        #: (episode, step) of the first and the last status it got.
        self.first_step: tuple[int, int] | None = None
        self.last_step: tuple[int, int] | None = None

    def done(self) -> bool:
        got = self.client.got
        return (self.track_seen and bool(got.get("/medc/map"))
                and all(len(got.get(t, [])) >= 3 for t in WANTED - {"/medc/map"}))

    def watch(self) -> None:
        """Receive until done or the deadline, then hang up."""
        try:
            self._watch()
        finally:
            self.close()

    def _watch(self) -> None:
        got = self.client.got
        while not (self.done() and self.until()) and time.monotonic() < self.deadline:
            before = {t: len(v) for t, v in got.items()}
            self.client.receive(timeout=0.5)
            if len(got.get("/medc/scene", [])) > before.get("/medc/scene", 0):
                if self.SceneUpdate is None:
                    self.SceneUpdate = _protobuf_class(self.client.channels["/medc/scene"]["schema"],
                                                       "foxglove.SceneUpdate")
                scene = self.SceneUpdate.FromString(got["/medc/scene"][-1])
                self.track_seen |= any(len(e.lines) and len(e.lines[0].points) > 1 for e in scene.entities
                                       if e.id.startswith("agent_"))
            if len(got.get("/medc/episode", [])) > before.get("/medc/episode", 0):
                s = _decoder(self.client.channels["/medc/episode"])(got["/medc/episode"][-1])
                self.last_step = (int(s.episode), int(s.step))
                self.first_step = self.first_step or self.last_step

    def close(self) -> None:
        self.client.ws.close()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timing
def test_foxglove_clients_connecting_early_mid_episode_and_late_get_the_map_episode_and_scene(
        bundles, tmp_path):
    """Three Foxglove clients: one connects as soon as the port opens (before the graph runs), one
    mid-episode, one in a later episode. Each gets the latched walls map, the episode status, the
    agents' topics and a scene with walls, agents and a track; no subscription meets an error."""
    import threading

    port = _free_port()
    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 2\nmax_steps: 20\nseed: 1\nmode: realtime\nrate_hz: 5.0\n"
                      f"policy: {bundles['a']}\n")
    err = (tmp_path / "stderr.txt").open("w")
    launcher = subprocess.Popen(
        [sys.executable, "-m", "medc_bringup.launcher", "--config", str(config), "--foxglove", str(port),
         "--timeout", "300"],
        stdout=subprocess.PIPE, stderr=err, text=True, start_new_session=True, cwd=tmp_path)
    viewers: dict[str, _Viewer] = {}
    threads: list[threading.Thread] = []
    try:
        deadline = time.monotonic() + 180

        def start(name: str, until=lambda: True) -> _Viewer:
            viewers[name] = viewer = _Viewer(port, deadline, until)
            threads.append(threading.Thread(target=viewer.watch, daemon=True))
            threads[-1].start()
            return viewer

        def wait_for(condition, what: str) -> None:
            while not condition():
                assert time.monotonic() < deadline, (
                    f"{what} never came; the early client saw {early.last_step}")
                time.sleep(0.05)

        early = start("early", until=lambda: "late" in viewers)  # it tells when to start the others
        wait_for(lambda: early.last_step is not None and early.last_step[1] >= 5, "step 5 of an episode")
        start("mid-episode")
        first_episode = early.last_step[0]
        wait_for(lambda: early.last_step[0] > first_episode, "a later episode")
        start("late")
        for t in threads:
            t.join(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        for v in viewers.values():
            v.close()
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
        out, _ = launcher.communicate(timeout=60)
        err.close()
    log = (tmp_path / "stderr.txt").read_text()
    assert launcher.returncode == 0, log[-3000:]
    assert "Traceback" not in log, log[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["recording"]["foxglove_port"] == port
    assert viewers["mid-episode"].first_step[1] > 0
    assert viewers["late"].first_step[0] > viewers["early"].first_step[0]
    for name, viewer in viewers.items():
        client, got = viewer.client, viewer.client.got
        counts = {t: len(got.get(t, [])) for t in sorted(WANTED)}
        assert viewer.done(), (f"{name} client: {counts}, track seen {viewer.track_seen}, errors "
                               f"{client.errors}; advertised {sorted(client.channels)}; log: {log[-2000:]}")
        assert not client.errors, f"{name} client: {client.errors}"

        # The raw ROS topics: CDR with their ros2msg schema, decodable by a ROS 2 client.
        status = client.channels["/medc/episode"]
        assert (status["encoding"], status["schemaEncoding"]) == ("cdr", "ros2msg")
        decode = _decoder(status)
        assert all(list(decode(b).agent_ids) == ["agent_0", "agent_1", "agent_2"]
                   for b in got["/medc/episode"])
        pose = _decoder(client.channels["/medc/agent_0/pose"])(got["/medc/agent_0/pose"][-1])
        assert pose.header.frame_id == "map" and 0 <= pose.pose.position.x <= 10

        # The scene: protobuf foxglove.SceneUpdate with the walls, each agent (reading) and status.
        scene_ch = client.channels["/medc/scene"]
        assert (scene_ch["encoding"], scene_ch["schemaName"]) == ("protobuf", "foxglove.SceneUpdate")
        last = {e.id: e for e in viewer.SceneUpdate.FromString(got["/medc/scene"][-1]).entities}
        assert {"walls", "agent_0", "agent_1", "agent_2", "status"} <= set(last)
        assert all(e.frame_id == "map" for e in last.values())
        assert len(last["walls"].cubes) > 0
        assert any(t.text.startswith("agent_0: ") and t.text.endswith(" cps") for t in last["agent_0"].texts)
        assert last["status"].texts[0].text.startswith("episode ")


def test_scene_places_walls_and_estimate_in_the_map_frame():
    """SceneState: walls at their cell centres (OccupancyGrid's layout, a translated origin), tracks
    per episode, and the estimate from a PoseWithCovarianceStamped on a topic named *estimate."""
    os.environ.setdefault("ROS_DOMAIN_ID", "0")
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from medc_bringup.live_view import SceneState, scene_update
    from medc_interfaces.msg import EpisodeStatus
    from nav_msgs.msg import OccupancyGrid

    state = SceneState("/medc")
    grid = OccupancyGrid()
    grid.info.width, grid.info.height, grid.info.resolution = 3, 2, 2.0
    grid.info.origin.position.x = 10.0
    grid.info.origin.orientation.w = 1.0
    grid.data = [0, 100, 0, 49, 0, 50]  # walls: (i=1, j=0) and (i=2, j=1)
    state.on_message("/medc/map", "nav_msgs/msg/OccupancyGrid", grid)
    assert state.walls == [(13.0, 1.0), (15.0, 3.0)]
    for episode, step, x in ((0, 0, 1.0), (0, 1, 3.0), (1, 0, 7.0)):
        pose = PoseStamped()
        pose.pose.position.x = x
        state.on_message("/medc/agent_0/pose", "geometry_msgs/msg/PoseStamped", pose)
        state.on_message("/medc/episode", "medc_interfaces/msg/EpisodeStatus",
                         EpisodeStatus(episode=episode, step=step))
        if (episode, step) == (0, 1):
            assert state.tracks["agent_0"] == [(1.0, 0.0), (3.0, 0.0)]
    assert state.tracks["agent_0"] == [(7.0, 0.0)]  # a new episode starts a new track
    est = PoseWithCovarianceStamped()
    est.pose.pose.position.x, est.pose.pose.position.y = 4.0, 5.0
    est.pose.covariance[0] = est.pose.covariance[7] = 4.0
    state.on_message("/medc/team/estimate", "geometry_msgs/msg/PoseWithCovarianceStamped", est)
    state.on_message("/other/team/estimate", "geometry_msgs/msg/PoseWithCovarianceStamped",
                     PoseWithCovarianceStamped())  # another namespace: not this team's
    assert state.estimate == (4.0, 5.0, 2.0)
    update = scene_update(state)
    SceneUpdate = _protobuf_class(base64.b64encode(update.get_schema().data).decode(), "foxglove.SceneUpdate")
    entities = {e.id: e for e in SceneUpdate.FromString(update.encode()).entities}
    assert [(c.pose.position.x, c.pose.position.y, c.size.x) for c in entities["walls"].cubes] == [
        (13.0, 1.0, 2.0), (15.0, 3.0, 2.0)]
    sphere = entities["estimate"].spheres[0]
    assert (sphere.pose.position.x, sphere.pose.position.y, sphere.size.x) == (4.0, 5.0, 4.0)
    assert entities["agent_0"].spheres[0].pose.position.x == 7.0


def test_scene_ignores_a_map_it_cannot_draw_and_keeps_the_last_one():
    """A map of width 0 with data (the view divided by it), one of 1500 x 1500 cells (a gigabyte of
    scene), data that does not match the size, a resolution or origin that is not finite: not drawn,
    the reason kept, the last good map still shown; non-finite poses, readings and estimates are
    not drawn either."""
    os.environ.setdefault("ROS_DOMAIN_ID", "0")
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from medc_bringup.live_view import SceneState
    from medc_interfaces.msg import RadiationReading
    from nav_msgs.msg import OccupancyGrid

    def grid(width: int, height: int, cells: int, resolution: float = 1.0, x: float = 0.0) -> OccupancyGrid:
        msg = OccupancyGrid()
        msg.info.width, msg.info.height, msg.info.resolution = width, height, resolution
        msg.info.origin.position.x = x
        msg.info.origin.orientation.w = 1.0
        msg.data = [100] * cells
        return msg

    state = SceneState("/medc")
    state.on_message("/medc/map", "nav_msgs/msg/OccupancyGrid", grid(2, 1, 2))
    good = list(state.walls)
    assert len(good) == 2 and state.map_refused is None
    state.take_changed()
    for bad, words in ((grid(0, 3, 3), "0 x 3 map"), (grid(1500, 1500, 1500 * 1500), "1500 x 1500"),
                       (grid(3, 3, 4), "4 data cells"),
                       (grid(2, 1, 2, resolution=float("nan")), "resolution"),
                       (grid(2, 1, 2, x=float("inf")), "origin")):
        state.on_message("/medc/map", "nav_msgs/msg/OccupancyGrid", bad)
        assert words in state.map_refused
        assert state.walls == good and not state.take_changed()
    pose = PoseStamped()
    pose.pose.position.x = float("nan")
    state.on_message("/medc/agent_0/pose", "geometry_msgs/msg/PoseStamped", pose)
    state.on_message("/medc/agent_0/radiation", "medc_interfaces/msg/RadiationReading",
                     RadiationReading(value=float("inf")))
    est = PoseWithCovarianceStamped()
    est.pose.pose.position.y = float("nan")
    state.on_message("/medc/team/estimate", "geometry_msgs/msg/PoseWithCovarianceStamped", est)
    assert state.agents == {} and state.readings == {} and state.estimate is None


def _subscribe_and_collect(port: int, topics: set[str], needed: str,
                           then_s: float = 0.5) -> dict[str, list[bytes]]:
    """Connect, subscribe to ``topics`` as they are advertised, collect data frames until ``needed``
    has a message (30 s at most), then ``then_s`` longer (for what must not come)."""
    deadline = time.monotonic() + 30
    with _connect(port, deadline) as ws:
        client = _Client(ws, topics)
        while not client.got.get(needed) and time.monotonic() < deadline:
            client.receive(timeout=0.2)
        end = time.monotonic() + then_s
        while time.monotonic() < end:
            client.receive(timeout=0.1)
    return client.got


@pytest.mark.timing
def test_a_client_that_connects_late_gets_the_latched_topics_last_message():
    """The walls map is published once per episode on a transient-local topic: a client that
    subscribes mid-episode gets the last map at once (as a late ROS subscriber would), and every
    later client too; a volatile topic's past messages are not replayed."""
    from medc_bringup.live_view import LiveView

    live = LiveView("/medc", port=0)
    try:
        live.add_topic("/medc/map", "std_msgs/msg/String", "string data", latched=True)
        live.add_topic("/medc/episode", "std_msgs/msg/String", "string data")
        for i in range(3):
            live.on_message("/medc/map", "std_msgs/msg/String", f"map {i}".encode())
            live.on_message("/medc/episode", "std_msgs/msg/String", f"step {i}".encode())
        for _ in range(2):
            got = _subscribe_and_collect(live.port, {"/medc/map", "/medc/episode"}, needed="/medc/map")
            assert got.get("/medc/map") == [b"map 2"]
            assert "/medc/episode" not in got
    finally:
        live.close()


@pytest.mark.timing
def test_declared_topics_are_in_the_greeting_and_a_late_unsubscribed_channel_is_advertised_again():
    """The topics given to LiveView are advertised when a client connects (no subscription can race
    their advertisement); a channel created while a client is connected that nobody subscribed to
    is advertised once more (a new id) on the next tick after READVERTISE_AFTER_S, and a late
    channel that has a subscriber is left alone."""
    from medc_bringup.live_view import LiveView

    live = LiveView("/medc", port=0, topics=[("/medc/map", "std_msgs/msg/String", "string data", True)])
    live.READVERTISE_AFTER_S = 0.2
    try:
        with _connect(live.port, time.monotonic() + 30) as ws:
            client = _Client(ws, {"/medc/map", "/medc/wanted"})
            deadline = time.monotonic() + 30

            def until(condition, what: str) -> None:
                while not condition():
                    assert time.monotonic() < deadline, (
                        f"{what}: advertised {({t: c['id'] for t, c in client.channels.items()})}")
                    client.receive(timeout=0.2)

            until(lambda: "/medc/map" in client.channels and "/medc/scene" in client.channels, "the greeting")
            live.add_topic("/medc/ignored", "std_msgs/msg/String", "string data")
            live.add_topic("/medc/wanted", "std_msgs/msg/String", "string data")
            until(lambda: {"/medc/ignored", "/medc/wanted"} <= set(client.channels), "the late channels")
            first = {t: client.channels[t]["id"] for t in ("/medc/ignored", "/medc/wanted")}
            # Wait until the server has the subscription to /medc/wanted, then let the delay pass.
            until(lambda: live.channels["/medc/wanted"].has_sinks(), "the subscription")
            time.sleep(0.3)
            live.tick()
            until(lambda: client.channels["/medc/ignored"]["id"] != first["/medc/ignored"],
                  "a re-advertisement")
            assert client.unadvertised == [first["/medc/ignored"]]
            assert client.channels["/medc/wanted"]["id"] == first["/medc/wanted"]
            live.tick()  # once per channel
            live.on_message("/medc/wanted", "std_msgs/msg/String", b"hello")
            until(lambda: client.got.get("/medc/wanted"), "the message")
            assert client.unadvertised == [first["/medc/ignored"]] and not client.errors
    finally:
        live.close()


def test_a_busy_port_or_a_missing_folder_is_refused_with_what_to_do(tmp_path, capsys):
    from medc_bringup.recorder import main

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["--foxglove", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"127.0.0.1:{port}" in err and "--foxglove PORT" in err
    assert main(["-o", str(tmp_path / "no" / "such" / "run.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([])  # nothing to do
