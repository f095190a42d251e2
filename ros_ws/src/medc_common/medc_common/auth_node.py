"""Message authentication on a node (medc_common.auth): its ``auth_key_file`` parameter, signing
what it publishes, checking what it takes, and the ``authentication`` condition on /diagnostics.

A :class:`NodeAuth` without a key (the open mode) signs nothing and takes everything, so a node's
code is the same in both modes. With a key, a message refused is counted by kind and reported as
WARN (the latest reason, the counts), and the condition is OK again :data:`CLEAR_S` seconds after
the last refusal. Poses and maps are taken only once a verified reading or status vouches for their
digest (:class:`Vouched`).
"""

from __future__ import annotations

import re
import struct
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from medc_common import auth
from medc_common.params import declare

#: Seconds without a refused message after which the ``authentication`` condition is OK again.
CLEAR_S = 5.0
#: The condition's name on /diagnostics.
CONDITION = "authentication"
#: The name of the status that carries a signed DiagnosticArray's Auth fields.
DIAGNOSTICS_AUTH = "auth"
KEY_FILE_HELP = (
    "Mission key file (medc-launch --authenticate writes one, 0600): sign every status, reading, "
    "move and declaration and take only verified ones; empty: $MEDC_AUTH_KEY_FILE, else the open "
    "mode (nothing signed or checked; docs/security.md)")


def type_name(msg) -> str:
    """``package/Type`` of a ROS message, e.g. ``medc_interfaces/AgentMove``."""
    return f"{type(msg).__module__.split('.')[0]}/{type(msg).__name__}"


#: numpy dtypes (fixed little-endian) of the ROS primitive types.
_DTYPES = {"double": "<f8", "float": "<f4", "int8": "i1", "uint8": "u1", "octet": "u1", "char": "u1",
           "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4", "int64": "<i8", "uint64": "<u8",
           "boolean": "?"}
_SCALARS = {**{k: struct.Struct("<" + f) for k, f in
               {"double": "d", "float": "f", "int16": "h", "uint16": "H", "int32": "i", "uint32": "I",
                "int64": "q", "uint64": "Q"}.items()},
            "int8": struct.Struct("<b"), "uint8": struct.Struct("<B"), "octet": struct.Struct("<B"),
            "char": struct.Struct("<B"), "boolean": struct.Struct("<?")}
_SEQUENCE = re.compile(r"^sequence<([^,>]+)(?:, *\d+)?>$")
_ARRAY = re.compile(r"^(.+)\[(\d+)\]$")
_LENGTH = struct.Struct("<I")
#: Per message type: how to encode each field, (name, encoder).
_PLANS: dict[type, list] = {}


def _encoder(ros_type: str) -> Callable[[Any, list], None]:
    """A function that appends the canonical bytes of a value of ``ros_type`` to a list."""
    m = _SEQUENCE.match(ros_type) or _ARRAY.match(ros_type)
    if m:
        element = m.group(1)
        if element in ("octet", "char"):  # a list of bytes of length 1 (or of ints)
            return lambda v, out: out.extend((_LENGTH.pack(len(v)), b"".join(
                x if isinstance(x, bytes) else bytes([x]) for x in v)))
        if element in _DTYPES:
            dtype = _DTYPES[element]
            return lambda v, out: out.extend((_LENGTH.pack(len(v)), np.asarray(v, dtype=dtype).tobytes()))
        item = _encoder(element)

        def sequence(v, out) -> None:
            out.append(_LENGTH.pack(len(v)))
            for x in v:
                item(x, out)
        return sequence
    if ros_type in _SCALARS:
        pack = _SCALARS[ros_type].pack
        if ros_type in ("octet", "char"):  # rclpy holds a byte as bytes of length 1, or an int
            return lambda v, out: out.append(bytes(v) if isinstance(v, bytes) else pack(v))
        return lambda v, out: out.append(pack(v))
    if ros_type in ("string", "wstring") or ros_type.startswith(("string<", "wstring<")):
        def text(v, out) -> None:
            data = v.encode("utf-8", "surrogatepass")
            out.extend((_LENGTH.pack(len(data)), data))
        return text
    return _encode_message  # a nested message


def _encode_message(msg, out: list) -> None:
    plan = _PLANS.get(type(msg))
    if plan is None:
        fields = msg.get_fields_and_field_types().items()
        plan = _PLANS[type(msg)] = [(name, _encoder(t)) for name, t in fields]
    for name, encode in plan:
        encode(getattr(msg, name), out)


def canonical(msg) -> bytes:
    """A canonical encoding of a ROS message: every field in declaration order, numbers
    little-endian at their declared width (a float32 rounded as the wire rounds it), strings and
    sequences length-prefixed. Not CDR: a re-serialised CDR message carries whatever was in memory
    in its alignment padding, so a receiver cannot reproduce the sender's bytes."""
    out: list[bytes] = []
    _encode_message(msg, out)
    return b"".join(out)


def message_digest(msg) -> bytes:
    """SHA-256 of a message's canonical encoding: a pose's or map's digest that a signed message
    carries."""
    return auth.digest(canonical(msg))


def _body(msg) -> tuple[bytes, bytes]:
    """(the message's canonical encoding with its MAC emptied, the MAC); the message is left as it
    was."""
    mac = bytes(msg.auth.mac)
    msg.auth.mac = b""
    try:
        return canonical(msg), mac
    finally:
        msg.auth.mac = mac


class NodeAuth:
    """One node's signing and checking (module docstring).

    ``key_file``: the node's ``auth_key_file`` setting ("" = :data:`auth.KEY_FILE_ENV`, else open
    mode); ``sender``: the node's per-run id; ``health``: its Health (None: not reported);
    ``logger``: its logger.
    """

    def __init__(self, key_file: str, sender: str, health=None, logger=None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        path = auth.key_file_setting(key_file)
        key = auth.load_key_file(path) if path else None  # AuthError: the node refuses to start
        self.enabled = key is not None
        self.signer = auth.Signer(key, sender) if key is not None else None
        self.verifier = auth.Verifier(key) if key is not None else None
        self.health = health
        self.logger = logger
        self.clock = clock
        #: Messages refused, by kind (status, reading, pose, map, move, declaration).
        self.refused: Counter[str] = Counter()
        self.last_refusal: float | None = None
        self._reported = 0.0

    def sign(self, msg, topic: str):
        """Sign ``msg`` for ``topic`` (fully qualified) in place and return it; unchanged when open."""
        if self.signer is None:
            return msg
        counter, stamp_ns = self.signer.next(topic)
        msg.auth.sender, msg.auth.counter, msg.auth.stamp_ns = self.signer.sender, counter, stamp_ns
        msg.auth.mac = b""
        msg.auth.mac = self.signer.mac(topic, type_name(msg), canonical(msg))
        return msg

    def admit(self, msg, topic: str, kind: str) -> bool:
        """Whether ``msg`` heard on ``topic`` may be used: always when open; with a key, only when its
        auth verifies (a refusal is counted and reported as ``kind``)."""
        if self.verifier is None:
            return True
        body, mac = _body(msg)
        a = msg.auth
        try:
            self.verifier.verify(topic, type_name(msg), body, mac, str(a.sender), int(a.counter),
                                 int(a.stamp_ns))
        except auth.AuthError as exc:
            self.refuse(kind, f"{kind} on {topic}: {exc}")
            return False
        return True

    def refuse(self, kind: str, reason: str) -> None:
        """Count a refused message of ``kind`` and report the condition (at most once a second)."""
        self.refused[kind] += 1
        now = self.clock()
        self.last_refusal = now
        if self.health is None or now - self._reported < 1.0:
            return
        self._reported = now
        counts = ", ".join(f"{n} {k}" for k, n in sorted(self.refused.items()))
        self.health.set(CONDITION, DiagnosticStatus.WARN, f"unauthenticated messages refused ({counts}); "
                        f"latest: {reason}", log=False)
        if self.logger is not None:
            self.logger.warning(f"refused unauthenticated {reason}")

    def check(self) -> None:
        """OK again once no message was refused for :data:`CLEAR_S` seconds (call from a timer)."""
        if self.last_refusal is None or self.health is None:
            return
        if self.clock() - self.last_refusal >= CLEAR_S:
            self.last_refusal = None
            self._reported = 0.0
            self.health.set(CONDITION, DiagnosticStatus.OK,
                            f"no unauthenticated message for {CLEAR_S:g} s "
                            f"(refused so far: {sum(self.refused.values())})")

    def sign_diagnostics(self, array, topic: str = "/diagnostics"):
        """Sign a DiagnosticArray (a heartbeat or an event) in place: one more status named
        ``auth`` whose values are the Auth fields (``sender``, ``counter``, ``stamp_ns``, ``mac`` in
        hex) over the array without it, so that a monitor holding the key can tell the team's
        health from a forger's (:meth:`admit_diagnostics`). Unchanged when open."""
        if self.signer is None:
            return array
        counter, stamp_ns = self.signer.next(topic)
        values = {"sender": self.signer.sender, "counter": str(counter), "stamp_ns": str(stamp_ns)}
        values["mac"] = self.signer.mac(topic, type_name(array), _diagnostics_body(array, values)).hex()
        array.status.append(DiagnosticStatus(name=DIAGNOSTICS_AUTH, values=_key_values(values)))
        return array

    def admit_diagnostics(self, array, topic: str = "/diagnostics") -> bool:
        """Whether a DiagnosticArray signed by :meth:`sign_diagnostics` verifies (always when open);
        its ``auth`` status is removed either way."""
        signed = array.status[-1] if array.status and array.status[-1].name == DIAGNOSTICS_AUTH else None
        if signed is not None:
            array.status = list(array.status[:-1])
        if self.verifier is None:
            return True
        values = {kv.key: kv.value for kv in signed.values} if signed is not None else {}
        try:
            mac = bytes.fromhex(values.pop("mac", ""))
            fields = {k: values[k] for k in ("sender", "counter", "stamp_ns")}
            self.verifier.verify(topic, type_name(array), _diagnostics_body(array, fields), mac,
                                 fields["sender"], int(fields["counter"]), int(fields["stamp_ns"]))
        except (KeyError, ValueError) as exc:
            why = exc if isinstance(exc, auth.AuthError) else "not signed (no auth status)"
            self.refuse("heartbeat", f"heartbeat on {topic}: {why}")
            return False
        return True

    def summary(self) -> dict[str, str]:
        """Heartbeat values: the mode and the refusals."""
        return {"authentication": "on" if self.enabled else "open",
                "auth_refused": str(sum(self.refused.values()))}


def _key_values(values: dict[str, str]) -> list:
    return [KeyValue(key=k, value=v) for k, v in values.items()]


def _diagnostics_body(array, fields: dict[str, str]) -> bytes:
    """What a signed DiagnosticArray's MAC covers: the array without its ``auth`` status, then that
    status's ``sender``, ``counter`` and ``stamp_ns`` values."""
    return canonical(array) + canonical(DiagnosticStatus(values=_key_values(fields)))


def declare_auth(node, sender: str, health=None) -> NodeAuth:
    """Declare ``auth_key_file`` on ``node`` and build its :class:`NodeAuth` (AuthError: a key file
    that cannot be used); with a key, a timer clears the condition."""
    key_file = str(declare(node, "auth_key_file", "", KEY_FILE_HELP, True))
    node_auth = NodeAuth(key_file, sender, health, node.get_logger())
    if health is not None:
        health.auth = node_auth  # its heartbeats and events are signed too
    if node_auth.enabled:
        node.create_timer(1.0, node_auth.check)
        node.get_logger().info("authenticated mode: signing and verifying the team's messages")
    return node_auth


class Vouched:
    """Standard messages (poses, maps) held until a verified message vouches for their digest.

    ``offer(key, msg)`` holds ``msg`` under ``key`` (e.g. (agent, stamp)); ``vouch(key, digest)``
    records the digest a verified message names and returns the held message that matches, if any;
    an offer whose key is vouched for already is returned at once when it matches. At most
    ``per_key`` candidates per key and ``keys`` keys are kept (the oldest go, counted as refused
    by ``on_refused``), so a flood of forgeries cannot grow it or push out the genuine one for long.
    """

    def __init__(self, on_refused: Callable[[str], None], keys: int = 64, per_key: int = 4) -> None:
        self.on_refused = on_refused
        self.keys = keys
        self.per_key = per_key
        self._held: OrderedDict[Any, list[tuple[bytes, Any]]] = OrderedDict()
        self._vouched: OrderedDict[Any, bytes] = OrderedDict()

    def offer(self, key, msg, digest: bytes):
        """``msg`` when it is vouched for already; else hold it and return None (a mismatch: refused)."""
        want = self._vouched.get(key)
        if want is not None:
            if want == digest:
                return msg
            self.on_refused(f"its digest is not the one its signed message names ({key})")
            return None
        held = self._held.setdefault(key, [])
        self._held.move_to_end(key)
        if any(d == digest for d, _ in held):
            return None
        held.append((digest, msg))
        if len(held) > self.per_key:
            held.pop(0)
            self.on_refused(f"more than {self.per_key} unvouched candidates for {key}")
        self._trim(self._held, counted=True)
        return None

    def vouch(self, key, digest: bytes):
        """Record that a verified message names ``digest`` for ``key``; the held match, or None."""
        self._vouched[key] = bytes(digest)
        self._vouched.move_to_end(key)
        self._trim(self._vouched, counted=False)
        held = self._held.pop(key, [])
        match = next((m for d, m in held if d == digest), None)
        for _ in range(len(held) - (match is not None)):
            self.on_refused(f"no signed message vouches for it ({key})")
        return match

    def _trim(self, table: OrderedDict, counted: bool) -> None:
        while len(table) > self.keys:
            _, value = table.popitem(last=False)
            if counted:
                for _ in value:
                    self.on_refused("never vouched for by a signed message")
