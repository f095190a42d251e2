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
            return connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=2)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


class _Client:
    """A Foxglove-protocol client: subscribes to each channel of ``wanted`` once, as advertised,
    and collects its data frames by topic (``got``); ``channels``: every advertised channel."""

    def __init__(self, ws, wanted: set[str]) -> None:
        self.ws, self.wanted = ws, wanted
        self.channels: dict[str, dict] = {}
        self.got: dict[str, list[bytes]] = {}
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
            return
        assert frame[0] == 0x01  # message data
        (sub_id,) = struct.unpack_from("<I", frame, 1)
        self.got.setdefault(self._subscribed[sub_id], []).append(bytes(frame[13:]))


@pytest.mark.ros
@pytest.mark.slow
def test_foxglove_client_receives_the_scene_and_the_topics(bundles, tmp_path):
    from mcap_ros2._dynamic import generate_dynamic

    port = _free_port()
    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 2\nmax_steps: 20\nseed: 1\nmode: realtime\nrate_hz: 5.0\n"
                      f"policy: {bundles['a']}\n")
    err = (tmp_path / "stderr.txt").open("w")
    launcher = subprocess.Popen(
        [sys.executable, "-m", "medc_bringup.launcher", "--config", str(config), "--foxglove", str(port),
         "--timeout", "120"],
        stdout=subprocess.PIPE, stderr=err, text=True, start_new_session=True, cwd=tmp_path)
    wanted = {"/medc/scene", "/medc/episode", "/medc/agent_0/pose", "/medc/agent_1/radiation", "/medc/map"}
    try:
        deadline = time.monotonic() + 90
        with _connect(port, deadline) as ws:
            client = _Client(ws, wanted)
            got = client.got
            while time.monotonic() < deadline:
                # ~3 s of steps at 5 Hz: the agents have moved (tracks) and read (labels).
                if (all(len(got.get(t, [])) >= 3 for t in wanted - {"/medc/map"}) and got.get("/medc/map")
                        and len(got["/medc/scene"]) >= 15):
                    break
                client.receive(timeout=1.0)
    finally:
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
        out, _ = launcher.communicate(timeout=60)
        err.close()
    log = (tmp_path / "stderr.txt").read_text()
    assert launcher.returncode == 0, log[-3000:]
    assert "Traceback" not in log, log[-3000:]
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["recording"]["foxglove_port"] == port
    channels = client.channels
    missing = {t: len(got.get(t, [])) for t in wanted if len(got.get(t, [])) < 1}
    assert not missing, f"no messages on {missing}; advertised {sorted(channels)}; log: {log[-2000:]}"

    # The raw ROS topics: CDR with their ros2msg schema, decodable by a ROS 2 client.
    status = channels["/medc/episode"]
    assert (status["encoding"], status["schemaEncoding"]) == ("cdr", "ros2msg")
    decode = generate_dynamic(status["schemaName"], status["schema"])[status["schemaName"]]
    steps = [decode(b) for b in got["/medc/episode"]]
    assert all(list(s.agent_ids) == ["agent_0", "agent_1", "agent_2"] for s in steps)
    pose_ch = channels["/medc/agent_0/pose"]
    pose = generate_dynamic(pose_ch["schemaName"], pose_ch["schema"])[pose_ch["schemaName"]](
        got["/medc/agent_0/pose"][-1])
    assert pose.header.frame_id == "map" and 0 <= pose.pose.position.x <= 10

    # The scene: protobuf foxglove.SceneUpdate with the walls, each agent (track, reading) and status.
    scene_ch = channels["/medc/scene"]
    assert (scene_ch["encoding"], scene_ch["schemaName"]) == ("protobuf", "foxglove.SceneUpdate")
    SceneUpdate = _protobuf_class(scene_ch["schema"], "foxglove.SceneUpdate")
    scenes = [SceneUpdate.FromString(b) for b in got["/medc/scene"]]
    last = {e.id: e for e in scenes[-1].entities}
    assert {"walls", "agent_0", "agent_1", "agent_2", "status"} <= set(last)
    assert all(e.frame_id == "map" for e in last.values())
    assert len(last["walls"].cubes) > 0
    assert any(len(e.lines) and len(e.lines[0].points) > 1 for s in scenes for e in s.entities
               if e.id.startswith("agent_")), "no agent track in any scene"
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


def _subscribe_and_collect(port: int, topics: set[str], seconds: float) -> dict[str, list[bytes]]:
    """Connect, subscribe to ``topics`` as they are advertised, collect data frames for ``seconds``."""
    deadline = time.monotonic() + seconds
    with _connect(port, deadline) as ws:
        client = _Client(ws, topics)
        while time.monotonic() < deadline:
            client.receive(timeout=0.2)
    return client.got


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
            got = _subscribe_and_collect(live.port, {"/medc/map", "/medc/episode"}, seconds=1.5)
            assert got.get("/medc/map") == [b"map 2"]
            assert "/medc/episode" not in got
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
    with pytest.raises(SystemExit) as exc:
        main(["-o", str(tmp_path / "no" / "such" / "run.mcap")])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([])  # nothing to do
