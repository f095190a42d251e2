"""Message-level authentication of the team's traffic (docs/security.md, "Authenticated mode").

The pinned Fast DDS has no DDS Security, so a mission started with ``medc-launch --authenticate``
proves who speaks at the message level instead: one random 32-byte key per mission, held in a
0600 file whose path every node is given (parameter ``auth_key_file`` or the environment variable
:data:`KEY_FILE_ENV`). Every status, reading, move and declaration carries a
``medc_interfaces/Auth`` field: the sender's per-run id, a counter, the sender's wall clock when it
signed, and an HMAC-SHA256 over :func:`signed_bytes` (a domain tag, the topic, the type name and the
message's canonical encoding with the MAC left empty,
:func:`medc_common.auth_node.canonical`). Poses and maps, standard messages with no room for a field,
are vouched for by digests in signed messages (a reading carries its pose's, a status its map's).

A receiver checks the MAC, then the freshness of the signing time (:data:`WINDOW_S` either side of
its own clock) and that the counter is above every counter it verified from that sender on that
topic (:class:`ReplayGuard`). This module is plain Python; :mod:`medc_common.auth_node` puts it on
nodes. Without a key nothing is signed or checked (the open mode).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import struct
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

#: Bytes of a mission key.
KEY_BYTES = 32
#: Bytes of a MAC (HMAC-SHA256) and of a digest (SHA-256).
MAC_BYTES = DIGEST_BYTES = 32
#: The environment variable naming the key file when a node's ``auth_key_file`` parameter is empty.
KEY_FILE_ENV = "MEDC_AUTH_KEY_FILE"
#: Seconds a message's signing time may be off the receiver's clock, either way.
WINDOW_S = 30.0
#: Senders whose counters a receiver remembers (per topic); the least recently heard go first.
MAX_SENDERS = 1024
#: What every MAC covers first, so that a MAC of this scheme is never valid for anything else.
DOMAIN = b"MEDC-AUTH-1\x00"


class AuthError(ValueError):
    """A message that is not authentic, not fresh or replayed; or a key file that cannot be used."""


def new_key() -> bytes:
    """A fresh mission key (:data:`KEY_BYTES` random bytes)."""
    return secrets.token_bytes(KEY_BYTES)


def write_key_file(path: str | os.PathLike[str], key: bytes | None = None) -> Path:
    """Write ``key`` (a new one when None) to a new file ``path`` readable by its owner only (0600),
    as hex text; returns the path. Never overwrites or follows a link (AuthError when ``path``
    exists)."""
    key = new_key() if key is None else key
    check_key(key)
    path = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags, 0o600)
    except FileExistsError:
        raise AuthError(f"key file {path} exists; pass it with --key-file to reuse it") from None
    except OSError as exc:
        raise AuthError(f"cannot create key file {path}: {exc.strerror}") from None
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    return path


def check_key(key: bytes) -> None:
    """AuthError unless ``key`` is :data:`KEY_BYTES` bytes."""
    if not isinstance(key, bytes) or len(key) != KEY_BYTES:
        raise AuthError(f"a mission key is {KEY_BYTES} bytes")


def load_key_file(path: str | os.PathLike[str]) -> bytes:
    """The key in ``path`` (written by :func:`write_key_file`).

    Raises:
        AuthError: the file is missing, not a regular file, readable or writable by anyone but its
        owner, or does not hold :data:`KEY_BYTES` bytes as hex.
    """
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        raise AuthError(f"key file {path} does not exist") from None
    except OSError as exc:
        raise AuthError(f"cannot open key file {path}: {exc.strerror}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise AuthError(f"key file {path} is not a regular file")
        if info.st_mode & 0o077:
            raise AuthError(f"key file {path} is open to other users (mode {stat.S_IMODE(info.st_mode):o}); "
                            "chmod 600 it")
        text = os.read(fd, 4 * KEY_BYTES).decode("ascii", "replace").strip()
    finally:
        os.close(fd)
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise AuthError(f"key file {path} must hold {KEY_BYTES} bytes as {2 * KEY_BYTES} hex digits")
    return key


def key_file_setting(parameter: str) -> str:
    """The key file a node uses: its ``auth_key_file`` parameter, else :data:`KEY_FILE_ENV`, else ""
    (the open mode)."""
    return parameter or os.environ.get(KEY_FILE_ENV, "")


def _field(data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + data


def signed_bytes(topic: str, type_name: str, body: bytes) -> bytes:
    """What a MAC covers: :data:`DOMAIN`, then ``topic`` (fully qualified), ``type_name`` and
    ``body`` (the message's canonical encoding with an empty MAC), each length-prefixed, so that a
    message signed for one topic or type is not valid on another."""
    return DOMAIN + _field(topic.encode()) + _field(type_name.encode()) + _field(body)


def compute_mac(key: bytes, topic: str, type_name: str, body: bytes) -> bytes:
    """HMAC-SHA256 under ``key`` of :func:`signed_bytes`."""
    return hmac.new(key, signed_bytes(topic, type_name, body), hashlib.sha256).digest()


def digest(data: bytes) -> bytes:
    """SHA-256 of ``data`` (a pose's or a map's canonical encoding that a signed message
    vouches for)."""
    return hashlib.sha256(data).digest()


class ReplayGuard:
    """Freshness and replay checks of verified messages: the signing time within ``window_s`` of
    ``clock_ns()`` and, per (sender, topic), a counter above every one seen before. Only messages
    whose MAC holds reach it, so only key holders add senders; at most ``max_senders`` are kept
    per topic (a forgotten sender's old messages are refused as stale, the window being shorter
    than any sender's life in the table)."""

    def __init__(self, window_s: float = WINDOW_S, clock_ns: Callable[[], int] = time.time_ns,
                 max_senders: int = MAX_SENDERS) -> None:
        if not window_s > 0:
            raise ValueError(f"freshness window must be > 0 s, got {window_s}")
        self.window_ns = int(window_s * 1e9)
        self.clock_ns = clock_ns
        self.max_senders = max_senders
        #: (topic, sender) -> highest counter verified.
        self._last: OrderedDict[tuple[str, str], int] = OrderedDict()

    def check(self, topic: str, sender: str, counter: int, stamp_ns: int) -> None:
        """Take the message or raise AuthError (stale, from the future, or replayed)."""
        skew = int(stamp_ns) - self.clock_ns()
        if abs(skew) > self.window_ns:
            side = "ahead of" if skew > 0 else "behind"
            raise AuthError(f"signed {abs(skew) / 1e9:.1f} s {side} this node's clock "
                            f"(window {self.window_ns / 1e9:g} s): stale or replayed")
        key = (topic, sender)
        last = self._last.get(key)
        if last is not None and counter <= last:
            raise AuthError(f"counter {counter} of sender {sender!r} not above {last}: replayed")
        self._last[key] = int(counter)
        self._last.move_to_end(key)
        while len(self._last) > self.max_senders:
            self._last.popitem(last=False)


class Signer:
    """Signs as one sender: ``sender`` (the node's per-run id) with a counter per topic that only
    grows, and the wall clock ``clock_ns`` as signing time."""

    def __init__(self, key: bytes, sender: str, clock_ns: Callable[[], int] = time.time_ns) -> None:
        check_key(key)
        if not sender:
            raise ValueError("a signer needs a sender id")
        self.key = key
        self.sender = sender
        self.clock_ns = clock_ns
        self._counters: dict[str, int] = {}

    def next(self, topic: str) -> tuple[int, int]:
        """(counter, signing time in ns) for the next message on ``topic``."""
        counter = self._counters.get(topic, 0) + 1
        self._counters[topic] = counter
        return counter, self.clock_ns()

    def mac(self, topic: str, type_name: str, body: bytes) -> bytes:
        return compute_mac(self.key, topic, type_name, body)


class Verifier:
    """Checks messages under one mission key: the MAC (constant-time compare), then the
    :class:`ReplayGuard`."""

    def __init__(self, key: bytes, guard: ReplayGuard | None = None) -> None:
        check_key(key)
        self.key = key
        self.guard = guard or ReplayGuard()

    def verify(self, topic: str, type_name: str, body: bytes, mac: bytes, sender: str, counter: int,
               stamp_ns: int) -> None:
        """Raise AuthError unless ``mac`` is the MAC of ``body`` on ``topic`` and the message is fresh
        and not replayed (``sender``, ``counter``, ``stamp_ns``: its Auth field, covered by the MAC
        through ``body``)."""
        if not sender:
            raise AuthError("not signed (no auth field): unauthenticated")
        if len(mac) != MAC_BYTES:
            raise AuthError(f"MAC of {len(mac)} bytes, expected {MAC_BYTES}")
        if not hmac.compare_digest(compute_mac(self.key, topic, type_name, body), bytes(mac)):
            raise AuthError(f"MAC does not verify (sender {sender[:40]!r}): forged, altered or another key")
        self.guard.check(topic, sender, counter, stamp_ns)
