"""A live view of a running MEDC graph for Foxglove: a WebSocket server (foxglove-sdk) on
127.0.0.1 that serves every recorded ROS topic as a channel (its CDR bytes, schema ``ros2msg``)
and a 3D scene, ``<namespace>/scene`` (``foxglove.SceneUpdate``, frame ``map``): the walls, the
agents with their tracks this episode and their latest readings, and the team's source estimate
when a topic under the namespace whose name holds ``estimate`` carries a pose or a point.

Open Foxglove, "Open connection", ``ws://127.0.0.1:PORT``, and add a 3D panel showing the scene
topic. The recorder (``medc_bringup.recorder``) feeds it; ``medc-launch --foxglove`` and
``medc-record --foxglove`` start it.

A client may connect at any moment and gets every channel: the scene and the contract's topics
(``topics``, declared before the server accepts a connection) are advertised in the server's
greeting, so no subscription races an advertisement. The SDK registers a channel advertised to a
client that is already connected only after sending the advertisement, and answers "Unknown
channel ID" to a subscription that arrives in between; a topic outside the declared ones
(discovered later) is served on a new channel, which such a client subscribes to once it is
registered: :class:`LiveView` re-advertises a late channel that a connected client left
unsubscribed (:meth:`LiveView.tick`).
"""

from __future__ import annotations

import math
import sys
import time

#: Foxglove's default port.
DEFAULT_PORT = 8765
#: The largest map side (cells) the scene draws: the contract's largest area (a team plays 5 to 64
#: cells a side). A larger map, or one whose data does not match its size, is not drawn (the
#: recording keeps it as it came).
MAX_MAP_SIDE = 64
#: Message types whose pose (or point) a topic named ``*estimate*`` contributes to the scene.
ESTIMATE_TYPES = (
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PointStamped",
)
#: One colour per agent (cycled).
PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
           (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5)]


class SceneState:
    """What the scene shows, built from the graph's messages (no Foxglove types: testable alone).

    ``on_message(topic, type_name, msg)`` takes a deserialised message; ``changed`` says a new
    team step (or map, or estimate) arrived since the last ``take_changed()``.
    """

    def __init__(self, namespace: str) -> None:
        self.ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
        self.walls: list[tuple[float, float]] = []
        self.resolution = 1.0
        self.agents: dict[str, tuple[float, float]] = {}
        self.tracks: dict[str, list[tuple[float, float]]] = {}
        self.readings: dict[str, float] = {}
        self.estimate: tuple[float, float, float] | None = None  # x, y, spread (m)
        self.episode = -1
        self.step = -1
        self.changed = False
        #: Why the last map was not drawn (None: it was).
        self.map_refused: str | None = None

    def on_message(self, topic: str, type_name: str, msg) -> None:
        """Update the state from one message of the graph."""
        rest = topic[len(self.ns):] if topic.startswith(self.ns + "/") else None
        if rest is None:
            return
        parts = rest.strip("/").split("/")
        if parts == ["map"] and type_name == "nav_msgs/msg/OccupancyGrid":
            self._on_map(msg)
        elif parts == ["episode"] and type_name == "medc_interfaces/msg/EpisodeStatus":
            self._on_status(msg)
        elif len(parts) == 2 and parts[1] == "pose" and type_name == "geometry_msgs/msg/PoseStamped":
            p = msg.pose.position
            if math.isfinite(p.x) and math.isfinite(p.y):  # a broken pose is not drawn
                self.agents[parts[0]] = (float(p.x), float(p.y))
        elif (len(parts) == 2 and parts[1] == "radiation"
              and type_name == "medc_interfaces/msg/RadiationReading"):
            if math.isfinite(msg.value):
                self.readings[parts[0]] = float(msg.value)
        elif "estimate" in parts[-1] and type_name in ESTIMATE_TYPES:
            self._on_estimate(type_name, msg)

    def _on_map(self, msg) -> None:
        info = msg.info
        o = info.origin
        q = o.orientation
        width, height, r = int(info.width), int(info.height), float(info.resolution)
        self.map_refused = map_problem(width, height, len(msg.data), r,
                                       (o.position.x, o.position.y, q.x, q.y, q.z, q.w))
        if self.map_refused is not None:
            return
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        c, s = math.cos(yaw), math.sin(yaw)
        walls = []
        for k, value in enumerate(msg.data):
            if value >= 50:
                i, j = k % width, k // width
                lx, ly = (i + 0.5) * r, (j + 0.5) * r
                walls.append((o.position.x + c * lx - s * ly, o.position.y + s * lx + c * ly))
        self.walls, self.resolution = walls, r
        self.changed = True

    def _on_status(self, msg) -> None:
        if int(msg.episode) != self.episode:
            self.episode = int(msg.episode)
            self.tracks = {}
        self.step = int(msg.step)
        for agent, xy in self.agents.items():
            track = self.tracks.setdefault(agent, [])
            if not track or track[-1] != xy:
                track.append(xy)
        self.changed = True

    def _on_estimate(self, type_name: str, msg) -> None:
        if type_name.endswith("PointStamped"):
            x, y, spread = msg.point.x, msg.point.y, 0.0
        elif type_name.endswith("PoseWithCovarianceStamped"):
            p, cov = msg.pose.pose.position, msg.pose.covariance
            x, y = p.x, p.y
            spread = math.sqrt(max(0.0, (float(cov[0]) + float(cov[7])) / 2.0))
        else:
            x, y, spread = msg.pose.position.x, msg.pose.position.y, 0.0
        if not all(math.isfinite(v) for v in (x, y, spread)):
            return
        self.estimate = (float(x), float(y), float(spread))
        self.changed = True

    def take_changed(self) -> bool:
        """True once per change (and clears it)."""
        changed, self.changed = self.changed, False
        return changed


def map_problem(width: int, height: int, cells: int, resolution: float,
                origin: tuple[float, ...]) -> str | None:
    """Why a map (an OccupancyGrid's width, height, number of data cells, resolution and origin
    position and orientation) cannot be drawn; None when it can."""
    if not (1 <= width <= MAX_MAP_SIDE and 1 <= height <= MAX_MAP_SIDE):
        return f"a {width} x {height} map (the scene draws 1 to {MAX_MAP_SIDE} cells a side)"
    if cells != width * height:
        return f"{cells} data cells for a {width} x {height} map"
    if not (math.isfinite(resolution) and resolution > 0):
        return f"resolution {resolution} (a positive number of metres per cell)"
    if not all(math.isfinite(v) for v in origin):
        return "an origin that is not a finite pose"
    return None


def scene_update(state: SceneState, stamp_ns: int | None = None):
    """The ``foxglove.messages.SceneUpdate`` that shows ``state`` (entities replace their
    predecessors by id: ``walls``, ``agent_i``, ``estimate``, ``status``)."""
    from foxglove.messages import (
        Color,
        CubePrimitive,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TextPrimitive,
        Timestamp,
        Vector3,
    )

    now = time.time_ns() if stamp_ns is None else stamp_ns
    ts = Timestamp(sec=now // 1_000_000_000, nsec=now % 1_000_000_000)
    r = state.resolution
    ident = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)

    def pose(x: float, y: float, z: float) -> Pose:
        return Pose(position=Vector3(x=x, y=y, z=z), orientation=ident)

    entities = [SceneEntity(
        timestamp=ts, frame_id="map", id="walls",
        cubes=[CubePrimitive(pose=pose(x, y, 0.5 * r), size=Vector3(x=r, y=r, z=r),
                             color=Color(r=0.35, g=0.35, b=0.4, a=1.0)) for x, y in state.walls],
    )]
    for k, agent in enumerate(sorted(state.agents)):
        cr, cg, cb = PALETTE[k % len(PALETTE)]
        color = Color(r=cr, g=cg, b=cb, a=1.0)
        x, y = state.agents[agent]
        reading = state.readings.get(agent)
        label = agent if reading is None else f"{agent}: {reading:.1f} cps"
        track = state.tracks.get(agent, [])
        points = [Point3(x=px, y=py, z=0.3 * r) for px, py in track]
        lines = [LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=pose(0.0, 0.0, 0.0),
                               thickness=0.08 * r, scale_invariant=False, points=points,
                               color=color)] if len(track) > 1 else []
        entities.append(SceneEntity(
            timestamp=ts, frame_id="map", id=agent,
            spheres=[SpherePrimitive(pose=pose(x, y, 0.5 * r), size=Vector3(x=0.6 * r, y=0.6 * r, z=0.6 * r),
                                     color=color)],
            lines=lines,
            texts=[TextPrimitive(pose=pose(x, y, 1.2 * r), billboard=True, font_size=14.0,
                                 scale_invariant=True, color=color, text=label)],
        ))
    if state.estimate is not None:
        x, y, spread = state.estimate
        d = max(0.4 * r, 2.0 * spread)
        entities.append(SceneEntity(
            timestamp=ts, frame_id="map", id="estimate",
            spheres=[SpherePrimitive(pose=pose(x, y, 0.1 * r), size=Vector3(x=d, y=d, z=0.1 * r),
                                     color=Color(r=1.0, g=0.84, b=0.0, a=0.6))],
            texts=[TextPrimitive(pose=pose(x, y, 0.8 * r), billboard=True, font_size=14.0,
                                 scale_invariant=True, color=Color(r=1.0, g=0.84, b=0.0, a=1.0),
                                 text="source estimate")],
        ))
    entities.append(SceneEntity(
        timestamp=ts, frame_id="map", id="status",
        texts=[TextPrimitive(pose=pose(0.0, -r, 0.0), billboard=True, font_size=16.0, scale_invariant=True,
                             color=Color(r=0.1, g=0.1, b=0.1, a=1.0),
                             text=f"episode {state.episode} step {state.step}")],
    ))
    return SceneUpdate(entities=entities)


class LiveView:
    """The Foxglove WebSocket server of a recorder: raw ROS topics as channels plus the scene.

    ``topics``: ``(topic, type name, ros2msg definition, latched)`` of every topic known before the
    server starts (the contract's); their channels and the scene's exist before a client can
    connect. ``port`` 0 picks a free port (``self.port`` tells which). The server binds ``127.0.0.1``.
    """

    #: Seconds after which a channel created while the server runs, still without a subscriber, is
    #: advertised once more (a client's subscription may have met the SDK's registration race).
    READVERTISE_AFTER_S = 1.0

    def __init__(self, namespace: str, port: int = DEFAULT_PORT, host: str = "127.0.0.1",
                 topics=()) -> None:
        import threading

        import foxglove
        from foxglove.channels import SceneUpdateChannel
        from foxglove.websocket import ServerListener

        view = self

        class _Resend(ServerListener):
            """A client that subscribes to a latched topic gets its last message at once (as a
            late ROS subscriber to a transient-local topic would): the walls map of an episode
            that began before the client connected."""

            def on_subscribe(self, client, channel) -> None:
                view._resend_latched(channel.topic)

        self._foxglove = foxglove
        self._lock = threading.Lock()
        self._last_scene = 0.0
        # A context of its own: this server's channels reach this server only.
        self.context = foxglove.Context()
        self.state = SceneState(namespace)
        self._map_refusal_said: str | None = None  # the map refusal last printed (said once each)
        self.scene_topic = f"{self.state.ns}/scene"
        self.scene = SceneUpdateChannel(self.scene_topic, context=self.context)
        self.channels: dict[str, object] = {}
        #: Latched (transient-local) topics and their last message, re-sent to each new subscriber.
        self.latched: dict[str, tuple[bytes, int | None] | None] = {}
        #: Channels created while serving, not yet confirmed subscribed or re-advertised: topic -> time.
        self._late: dict[str, float] = {}
        self.serving = False
        for topic, type_name, definition, latched in topics:
            self.add_topic(topic, type_name, definition, latched)
        self.server = foxglove.start_server(name="medc", host=host, port=int(port), server_listener=_Resend(),
                                            context=self.context)
        self.serving = True
        self.port = int(self.server.port)

    def _channel(self, topic: str, schema):
        return self._foxglove.Channel(topic, message_encoding="cdr", schema=schema, context=self.context)

    def add_topic(self, topic: str, type_name: str, definition: str, latched: bool = False) -> None:
        """Serve ``topic`` as a channel (CDR bytes, its ``ros2msg`` schema text); ``latched``: the
        topic is transient local, and a client that subscribes gets its last message at once."""
        if topic in self.channels:
            return
        if latched:
            with self._lock:
                self.latched[topic] = None
        schema = self._foxglove.Schema(name=type_name, encoding="ros2msg", data=definition.encode())
        self.channels[topic] = self._channel(topic, schema)
        if self.serving:
            self._late[topic] = time.monotonic()

    def _readvertise_late(self) -> None:
        """Advertise again (a new channel id) each late channel that nobody subscribed to within
        READVERTISE_AFTER_S; a subscribed one is left alone. Once per channel."""
        now = time.monotonic()
        for topic, created in list(self._late.items()):
            if now - created < self.READVERTISE_AFTER_S:
                continue
            del self._late[topic]
            old = self.channels[topic]
            if old.has_sinks():
                continue
            old.close()  # first: the SDK hands out a topic's open channel again
            self.channels[topic] = self._channel(topic, old.schema())

    def _resend_latched(self, topic: str) -> None:
        with self._lock:
            last = self.latched.get(topic)
        if last is not None:
            data, log_time_ns = last
            self.channels[topic].log(data, log_time=log_time_ns)

    def on_message(self, topic: str, type_name: str, data: bytes, msg=None,
                   log_time_ns: int | None = None) -> None:
        """Forward one message (its CDR ``data``; ``msg``: it deserialised, when the scene uses it)."""
        channel = self.channels.get(topic)
        if channel is not None:
            if topic in self.latched:
                with self._lock:
                    self.latched[topic] = (bytes(data), log_time_ns)
            channel.log(data, log_time=log_time_ns)
        if msg is not None:
            self.state.on_message(topic, type_name, msg)
            refused = self.state.map_refused
            if refused is not None and refused != self._map_refusal_said:
                print(f"live view: not drawing the map on {topic}: {refused}", file=sys.stderr, flush=True)
            self._map_refusal_said = refused
            if self.state.take_changed():
                self.publish_scene(log_time_ns)

    def publish_scene(self, log_time_ns: int | None = None) -> None:
        """Send the scene now."""
        self.scene.log(scene_update(self.state, log_time_ns), log_time=log_time_ns)
        self._last_scene = time.monotonic()

    def tick(self, every_s: float = 1.0) -> None:
        """Re-send the scene when nothing changed for ``every_s`` (a client that just connected
        sees the walls of an idle graph); advertise unsubscribed late channels once more."""
        if time.monotonic() - self._last_scene >= every_s:
            self.publish_scene()
        if self._late:
            self._readvertise_late()

    def wants(self, topic: str, type_name: str) -> bool:
        """Whether the scene needs ``topic`` deserialised."""
        ns = self.state.ns
        if not topic.startswith(ns + "/"):
            return False
        last = topic.rsplit("/", 1)[-1]
        return (last in ("map", "episode", "pose", "radiation")
                or ("estimate" in last and type_name in ESTIMATE_TYPES))

    def close(self) -> None:
        """Stop the server."""
        self.server.stop()
