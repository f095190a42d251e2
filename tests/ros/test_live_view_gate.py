"""The live view against hostile web pages and connection floods: a page of another origin (and
``null``) is refused with a close reason (1008) before the Foxglove server sees it, a connection
beyond the cap with another (1013, try again later), a request that never comes or is no
WebSocket opening is dropped or answered 403; the clients served keep getting the mission's
messages throughout, and a refused slot is free again once a client leaves."""

from __future__ import annotations

import contextlib
import socket
import time

import pytest

#: Seconds a loaded machine is given for what these tests wait on (the deadline, not a sleep).
DEADLINE_S = 30.0


def _connect(port: int, origin: str | None = None):
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=DEADLINE_S,
                   close_timeout=DEADLINE_S, ping_interval=None, origin=origin)


def _refusal(ws) -> tuple[int, str]:
    """The close code and reason of a connection the gate refused."""
    from websockets.exceptions import ConnectionClosed

    with pytest.raises(ConnectionClosed) as closed:
        while True:
            ws.recv(timeout=DEADLINE_S)
    rcvd = closed.value.rcvd
    assert rcvd is not None, "closed without a reason"
    return rcvd.code, rcvd.reason


def _greeted(ws) -> dict:
    """The Foxglove server's greeting (serverInfo): the connection reached the server."""
    import json

    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        frame = ws.recv(timeout=DEADLINE_S)
        if isinstance(frame, str) and json.loads(frame).get("op") == "serverInfo":
            return json.loads(frame)
    raise AssertionError("no serverInfo from the server")


@pytest.fixture()
def live():
    from medc_bringup.live_view import LiveView

    view = LiveView("/medc", port=0, max_clients=2,
                    topics=[("/medc/map", "std_msgs/msg/String", "string data", True)])
    yield view
    view.close()


def test_the_origin_rule():
    from medc_bringup.live_view import origin_allowed

    for ok in (None, "http://localhost:3000", "https://127.0.0.1", "http://[::1]:8080", "http://app.localhost"):
        assert origin_allowed(ok), ok
    for bad in ("https://evil.example", "null", "http://127.0.0.1.evil.example", "file://", "ws://localhost",
                "http://localhost:notaport", "https://app.foxglove.dev"):
        assert not origin_allowed(bad), bad
    assert origin_allowed("https://app.foxglove.dev", ("https://app.foxglove.dev",))


@pytest.mark.timing
def test_a_foreign_origin_is_refused_with_a_reason_and_a_local_one_served(live):
    for origin in ("https://evil.example", "null"):
        with _connect(live.port, origin) as ws:
            code, reason = _refusal(ws)
        assert code == 1008 and reason == (f"origin {origin} refused: the live view serves this machine's "
                                           "pages only")
    assert live.gate.refused["origin"] == 2 and live.gate.served == 0  # the server never saw them
    for origin in (None, "http://localhost:8080"):
        with _connect(live.port, origin) as ws:
            assert _greeted(ws)["op"] == "serverInfo"
    assert live.gate.served == 2


@pytest.mark.timing
def test_connections_beyond_the_cap_are_refused_and_the_served_keep_their_messages(live):
    import json

    stack = contextlib.ExitStack()
    first, second = stack.enter_context(_connect(live.port)), stack.enter_context(_connect(live.port))
    with stack:
        for ws in (first, second):
            _greeted(ws)
        extra = []
        for _ in range(20):  # a flood: each refused at once, none of them reaches the server
            with _connect(live.port) as ws:
                extra.append(_refusal(ws))
        assert set(extra) == {(1013, "too many connections: the live view serves 2 at once")}
        assert live.gate.refused["clients"] == 20 and live.gate.active == 2
        # The served clients still get the mission: subscribe to the map and receive it.
        deadline = time.monotonic() + DEADLINE_S
        channel = None
        while channel is None and time.monotonic() < deadline:
            frame = first.recv(timeout=DEADLINE_S)
            if isinstance(frame, str) and json.loads(frame).get("op") == "advertise":
                channel = next((c["id"] for c in json.loads(frame)["channels"] if c["topic"] == "/medc/map"),
                               None)
        assert channel is not None
        first.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel}]}))
        while not live.channels["/medc/map"].has_sinks() and time.monotonic() < deadline:
            time.sleep(0.05)
        live.on_message("/medc/map", "std_msgs/msg/String", b"walls")
        got = None
        while got is None and time.monotonic() < deadline:
            frame = first.recv(timeout=DEADLINE_S)
            if isinstance(frame, bytes) and frame[0] == 1:  # message data
                got = frame[1 + 4 + 8:]
        assert got == b"walls"
    deadline = time.monotonic() + DEADLINE_S
    while live.gate.active and time.monotonic() < deadline:
        time.sleep(0.05)
    with _connect(live.port) as ws:  # the slots are free again
        _greeted(ws)


@pytest.mark.timing
def test_a_request_that_is_no_websocket_opening_or_never_comes(live, monkeypatch):
    with socket.create_connection(("127.0.0.1", live.port), timeout=DEADLINE_S) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nOrigin: https://evil.example\r\n\r\n")
        answer = b""
        while chunk := sock.recv(4096):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 403 Forbidden") and b"origin https://evil.example refused" in answer
    from medc_bringup import live_view

    monkeypatch.setattr(live_view, "REQUEST_TIMEOUT_S", 0.5)
    with socket.create_connection(("127.0.0.1", live.port), timeout=DEADLINE_S) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\n")  # and nothing more
        assert sock.recv(4096) == b""  # closed, unanswered, once the request is overdue
    assert live.gate.refused["request"] == 1 and live.gate.active == 0


def test_launch_passes_the_live_view_options_to_its_recorder(monkeypatch):
    """medc-launch --foxglove --foxglove-clients N --foxglove-origin O starts medc-record with them."""
    import subprocess

    from medc_bringup import recorder
    from medc_bringup.launcher import LaunchConfig

    started = {}
    monkeypatch.setattr(subprocess, "Popen", lambda command, **_: started.setdefault("command", command))
    recorder.start_recorder(LaunchConfig(agents=2), None, 0, foxglove_clients=3,
                            foxglove_origins=("https://app.foxglove.dev",))
    command = started["command"]
    assert command[command.index("--foxglove-clients") + 1] == "3"
    assert command[command.index("--foxglove-origin") + 1] == "https://app.foxglove.dev"
    assert recorder.build_parser().parse_args(command[3:]).foxglove_origin == ["https://app.foxglove.dev"]
