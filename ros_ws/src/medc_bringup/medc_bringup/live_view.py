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

import contextlib
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


# ---------------------------------------------------------------- the connection gate
#: Connections the live view serves at once unless told otherwise (medc-record --foxglove-clients):
#: a few Foxglove windows; each costs the server memory and a copy of every message.
DEFAULT_MAX_CLIENTS = 8
#: Connections that have not finished their opening request yet; more are closed unanswered.
MAX_PENDING = 64
#: Seconds a connection has to send its opening request, and the largest one taken (bytes).
REQUEST_TIMEOUT_S = 5.0
MAX_REQUEST_BYTES = 16384
#: Host names of a web page's origin the live view accepts: this machine's.
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")
#: WebSocket close codes of a refusal (RFC 6455): policy violation, try again later.
CLOSE_POLICY = 1008
CLOSE_TRY_LATER = 1013
_WS_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"


def origin_allowed(origin: str | None, allowed: tuple[str, ...] = ()) -> bool:
    """Whether a WebSocket opening request with this ``Origin`` header is served: none (a client
    that is no web page: Foxglove's desktop app, a script), a page served by this machine
    (``http(s)://localhost``, ``127.0.0.1`` or ``[::1]``, any port, or ``*.localhost``), or one of
    ``allowed`` (exact origins the user named, e.g. ``https://app.foxglove.dev``). Any other web
    page, ``null`` (a sandboxed or local-file page) included, is refused: a page the user merely
    visits must not read the mission."""
    if origin is None:
        return True
    origin = origin.strip()
    if origin in allowed:
        return True
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(origin)
        host = (parts.hostname or "").lower()
        parts.port  # noqa: B018 - a port that is not a number raises here
    except ValueError:
        return False
    return parts.scheme in ("http", "https") and (host in LOOPBACK_HOSTS or host.endswith(".localhost"))


def _close_frame(code: int, reason: str) -> bytes:
    """An unmasked WebSocket close frame (server to client) with ``code`` and ``reason`` (cut to
    the 123 bytes a control frame may carry)."""
    payload = code.to_bytes(2, "big") + reason.encode()[:123]
    return bytes([0x88, len(payload)]) + payload


def _parse_request(head: bytes) -> tuple[str, dict[str, str]]:
    """(request line, headers by lower-case name) of an HTTP request head."""
    lines = head.decode("latin-1").split("\r\n")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if sep:
            headers[name.strip().lower()] = value.strip()
    return lines[0], headers


class ConnectionGate:
    """What stands between a client and the Foxglove server (which has no hook for either): a TCP
    listener on ``host``:``port`` that reads each connection's opening request and serves it (passes
    it and everything after it to the server on ``upstream``) only when its web ``Origin`` is
    allowed (:func:`origin_allowed`) and fewer than ``max_clients`` connections are served.
    Otherwise it completes the WebSocket handshake and closes with a reason a client shows: 1008
    for an origin, 1013 (try again later) for one connection too many; a request that is no
    WebSocket opening gets an HTTP 403 with the reason. A request must come within
    REQUEST_TIMEOUT_S and fit MAX_REQUEST_BYTES; more than MAX_PENDING connections still to send
    theirs are closed unanswered. It runs an asyncio loop in a thread of its own.

    ``refused`` counts the refusals by kind (``origin``, ``clients``, ``request``), ``served`` the
    connections served so far; ``active`` is the number served now.
    """

    def __init__(self, upstream: int, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 max_clients: int = DEFAULT_MAX_CLIENTS, allowed_origins: tuple[str, ...] = ()) -> None:
        import asyncio
        import threading

        if max_clients < 1:
            raise ValueError(f"max_clients must be at least 1, got {max_clients}")
        self.upstream = int(upstream)
        self.max_clients = int(max_clients)
        self.allowed_origins = tuple(allowed_origins)
        self.active = 0
        self.pending = 0
        self.served = 0
        self.refused = {"origin": 0, "clients": 0, "request": 0}
        self._writers: set = set()
        self._loop = asyncio.new_event_loop()
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(self._handle, host, int(port), reuse_address=True,
                                     limit=MAX_REQUEST_BYTES))
        except BaseException:
            self._loop.close()
            raise
        self.port = int(self._server.sockets[0].getsockname()[1])
        self._thread = threading.Thread(target=self._loop.run_forever, name="live-view-gate", daemon=True)
        self._thread.start()

    async def _handle(self, reader, writer) -> None:
        import asyncio

        from medc_training.untrusted import printable

        self._writers.add(writer)
        try:
            if self.pending >= MAX_PENDING:
                self.refused["request"] += 1
                return
            self.pending += 1
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
            except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
                self.refused["request"] += 1
                return
            finally:
                self.pending -= 1
            if len(head) > MAX_REQUEST_BYTES:
                self.refused["request"] += 1
                return
            _, headers = _parse_request(head)
            origin = headers.get("origin")
            if not origin_allowed(origin, self.allowed_origins):
                self.refused["origin"] += 1
                await self._refuse(writer, headers, CLOSE_POLICY,
                                   f"origin {printable(origin, 60)} refused: the live view serves this "
                                   "machine's pages only")
                return
            if self.active >= self.max_clients:
                self.refused["clients"] += 1
                await self._refuse(writer, headers, CLOSE_TRY_LATER,
                                   f"too many connections: the live view serves {self.max_clients} at once")
                return
            self.active += 1
            self.served += 1
            try:
                await self._serve(head, reader, writer)
            finally:
                self.active -= 1
        except Exception:  # a connection's trouble is that connection's only
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _serve(self, head: bytes, reader, writer) -> None:
        import asyncio

        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream)
        self._writers.add(up_writer)
        up_writer.write(head)

        async def pipe(source, sink) -> None:
            try:
                while data := await source.read(1 << 16):
                    sink.write(data)
                    await sink.drain()
            except (ConnectionError, OSError):
                pass
            finally:
                sink.close()

        try:
            await asyncio.gather(pipe(reader, up_writer), pipe(up_reader, writer))
        finally:
            self._writers.discard(up_writer)
            up_writer.close()

    async def _refuse(self, writer, headers: dict[str, str], code: int, reason: str) -> None:
        """Answer a refused request: the handshake and a close frame with ``reason`` (a WebSocket
        opening), or an HTTP 403 with it."""
        import asyncio
        import base64
        import hashlib

        key = headers.get("sec-websocket-key")
        if key and headers.get("upgrade", "").lower() == "websocket":
            accept = base64.b64encode(hashlib.sha1((key + _WS_GUID).encode()).digest()).decode()
            protocol = headers.get("sec-websocket-protocol", "").split(",")[0].strip()
            answer = ("HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                      f"Sec-WebSocket-Accept: {accept}\r\n"
                      + (f"Sec-WebSocket-Protocol: {protocol}\r\n" if protocol else "") + "\r\n")
            writer.write(answer.encode("latin-1") + _close_frame(code, reason))
        else:
            body = (reason + "\n").encode()
            writer.write(b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain; charset=utf-8\r\n"
                         + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body)
        with contextlib.suppress(TimeoutError, ConnectionError):
            await asyncio.wait_for(writer.drain(), REQUEST_TIMEOUT_S)

    def close(self) -> None:
        """Stop listening and close every connection (idempotent)."""
        if self._loop.is_closed():
            return

        def stop() -> None:
            import asyncio

            self._server.close()
            for writer in list(self._writers):
                writer.close()
            for task in asyncio.all_tasks(self._loop):  # each connection's task ends, none left pending
                task.cancel()
            self._loop.call_soon(self._loop.stop)  # after the cancellations have run

        self._loop.call_soon_threadsafe(stop)
        self._thread.join(timeout=10)
        if not self._thread.is_alive():
            self._loop.close()


class LiveView:
    """The Foxglove WebSocket server of a recorder: raw ROS topics as channels plus the scene.

    ``topics``: ``(topic, type name, ros2msg definition, latched)`` of every topic known before the
    server starts (the contract's); their channels and the scene's exist before a client can
    connect. ``port`` 0 picks a free port (``self.port`` tells which). Clients reach the server
    through a :class:`ConnectionGate` on ``host`` (``127.0.0.1``): a web page from elsewhere
    (its ``Origin``, unless in ``allowed_origins``) and a connection beyond ``max_clients`` are
    refused with a close reason. The Foxglove server itself listens on another loopback port.
    """

    #: Seconds after which a channel created while the server runs, still without a subscriber, is
    #: advertised once more (a client's subscription may have met the SDK's registration race).
    READVERTISE_AFTER_S = 1.0

    def __init__(self, namespace: str, port: int = DEFAULT_PORT, host: str = "127.0.0.1",
                 topics=(), max_clients: int = DEFAULT_MAX_CLIENTS,
                 allowed_origins: tuple[str, ...] = ()) -> None:
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
        self.server = foxglove.start_server(name="medc", host="127.0.0.1", port=0, server_listener=_Resend(),
                                            context=self.context)
        try:
            self.gate = ConnectionGate(int(self.server.port), host=host, port=int(port),
                                       max_clients=max_clients, allowed_origins=allowed_origins)
        except BaseException:
            self.server.stop()
            raise
        self.serving = True
        self.port = self.gate.port

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
        """Stop the gate and the server."""
        self.gate.close()
        self.server.stop()
