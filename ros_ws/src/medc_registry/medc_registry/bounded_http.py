"""HTTP to outside nodes with one total deadline and a size cap: headers included.

A socket timeout bounds each read, not an answer: a node that drips one header byte (or one body
byte) per second keeps ``requests``, ``httpx`` and a plain ``http.client`` response alive for as
long as it likes. Here every receive, from the status line to the last body byte, first sets the
socket's timeout to what is left of the answer's deadline, so an answer ends at its deadline
whatever the node does; bodies are read up to a cap and refused past it (:class:`BodyTooLarge`),
so an endless answer cannot exhaust memory.

Used by the JSON-RPC provider of :class:`medc_registry.chain.ChainClient` and by the Kubo RPC
client :class:`medc_registry.content.KuboContentStore` (``cat``, ``block/get``, ``add``, pins).
"""

from __future__ import annotations

import contextlib
import http.client
import io
import time
from collections.abc import Callable, Iterator
from typing import Any
from urllib.parse import urlsplit


class DeadlineExceeded(TimeoutError):
    """The answer did not arrive in full before its deadline."""


class BodyTooLarge(ValueError):
    """An answer (declared or received) over the caller's size cap; refused, not read on."""


class _DeadlineRaw(io.RawIOBase):
    """The socket's bytes, each receive bounded by what is left of the deadline."""

    def __init__(self, sock: Any, left: Callable[[], float]) -> None:
        self._sock = sock
        self._left = left

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        self._sock.settimeout(self._left())
        return self._sock.recv_into(buffer)


class _DeadlineSocket:
    """A connected socket whose reads (through ``makefile``, as http.client reads a response) and
    writes never outlast the deadline."""

    def __init__(self, sock: Any, left: Callable[[], float]) -> None:
        self._sock = sock
        self._left = left

    def makefile(self, mode: str = "rb", *args: Any, **kwargs: Any) -> io.BufferedReader:
        if "r" not in mode or "w" in mode:
            raise ValueError("only reading through makefile is supported")
        return io.BufferedReader(_DeadlineRaw(self._sock, self._left))

    def sendall(self, data: Any) -> None:
        self._sock.settimeout(self._left())
        self._sock.sendall(data)

    def close(self) -> None:
        """Nothing yet: http.client closes the connection while the response still reads from it
        (a body that ends at close); :func:`open_post` closes the socket when done."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def _connection(url: str, left: Callable[[], float]) -> http.client.HTTPConnection:
    parts = urlsplit(url)
    base = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection

    class Connection(base):  # type: ignore[valid-type, misc]
        raw_sock: Any = None

        def connect(self) -> None:
            self.timeout = left()
            super().connect()
            self.raw_sock = self.sock
            self.sock = _DeadlineSocket(self.sock, left)

    default = 443 if parts.scheme == "https" else 80
    return Connection(parts.hostname or "127.0.0.1", parts.port or default)


def deadline_clock(until: float, timeout: float, late: Callable[[], BaseException]) -> Callable[[], float]:
    """Seconds one socket operation may wait: at most ``timeout``, never past ``until``
    (``time.monotonic()`` time); raises ``late()`` once ``until`` has passed."""

    def left() -> float:
        remaining = until - time.monotonic()
        if remaining <= 0:
            raise late()
        return min(timeout, remaining)

    return left


@contextlib.contextmanager
def open_post(
    url: str, target: str, body: bytes, headers: dict[str, str], left: Callable[[], float]
) -> Iterator[http.client.HTTPResponse]:
    """POST ``body`` to ``target`` (path and query) on the server of ``url``; yields the response
    with its status line and headers read, every receive bounded by ``left()`` (see
    :func:`deadline_clock`). The connection is closed on leaving."""
    conn = _connection(url, left)
    try:
        conn.request("POST", target, body=body, headers=headers)
        yield conn.getresponse()
    finally:
        conn.close()
        if conn.raw_sock is not None:
            conn.raw_sock.close()


def declared_length(resp: http.client.HTTPResponse) -> int | None:
    """The body length the server declared (``X-Content-Length`` or ``Content-Length``), if any."""
    for header in ("X-Content-Length", "Content-Length"):
        value = resp.getheader(header)
        if value and value.strip().isdigit():
            return int(value.strip())
    return None


def read_capped(resp: http.client.HTTPResponse, max_body: int, what: str) -> bytes:
    """The whole body of ``resp``, refused with :class:`BodyTooLarge` past ``max_body`` bytes
    (declared or received: nothing past the cap is read)."""
    declared = declared_length(resp)
    if declared is not None and declared > max_body:
        raise BodyTooLarge(f"{what}: the answer declares {declared} bytes, over the {max_body} byte limit")
    out = bytearray()
    while chunk := resp.read1(1 << 16):
        out += chunk
        if len(out) > max_body:
            raise BodyTooLarge(f"{what}: the answer is over the {max_body} byte limit; refused while reading")
    return bytes(out)


def post(
    url: str,
    target: str,
    body: bytes,
    headers: dict[str, str],
    *,
    until: float,
    timeout: float,
    max_body: int,
    what: str,
) -> tuple[int, bytes]:
    """(status, body) of one POST, all of it before ``until`` (``time.monotonic()`` time) and no
    body over ``max_body`` bytes: :class:`DeadlineExceeded`, :class:`BodyTooLarge`, or the
    ``OSError`` / ``http.client.HTTPException`` of a broken connection."""
    late = lambda: DeadlineExceeded(f"{what}: no complete answer from {url} within the deadline")  # noqa: E731
    with open_post(url, target, body, headers, deadline_clock(until, timeout, late)) as resp:
        return resp.status, read_capped(resp, max_body, what)
