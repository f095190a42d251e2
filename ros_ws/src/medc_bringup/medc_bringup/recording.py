"""Recording a MEDC graph as rosbag2 does with its MCAP storage: the parts that need no node.

An MCAP file of profile ``ros2``: one schema per message type, encoding ``ros2msg``, whose text
is the type's ``.msg`` definition followed by those of every type it uses (each after a line of
80 ``=`` and ``MSG: pkg/Type``, as rosbag2 and ``mcap_ros2`` write and read them); one channel per
topic, message encoding ``cdr``, with the ``offered_qos_profiles`` metadata rosbag2 records; the
messages as the CDR bytes received. ``rosbags`` (``rosbags.rosbag2.Reader``), ``mcap_ros2``'s
decoder and Foxglove read such a file.

The ``.msg`` definitions come from the installed packages' share folders (the ament index):
``medc_interfaces`` from the colcon build under ``ros_ws/install``, the standard ones from the
ROS wheels.
"""

from __future__ import annotations

import importlib
import re
import time
from functools import cache
from pathlib import Path
from typing import IO

from mcap.writer import CompressionType, Writer

#: Field types of the ROS 2 IDL that are not messages.
PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})
_SEPARATOR = "=" * 80


def split_type(type_name: str) -> tuple[str, str]:
    """``("pkg", "Type")`` of ``pkg/msg/Type`` or ``pkg/Type``.

    Raises:
        ValueError: not a message type name.
    """
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise ValueError(f"{type_name!r} is not a message type (expected pkg/msg/Type)")


@cache
def msg_file_text(package: str, name: str) -> str:
    """The text of ``share/<package>/msg/<name>.msg`` of the installed package.

    Raises:
        ValueError: the package or its definition is not installed; says what to do.
    """
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        share = Path(get_package_share_directory(package))
    except PackageNotFoundError:
        raise ValueError(
            f"cannot find the message package {package!r} on AMENT_PREFIX_PATH (for medc_interfaces: "
            "run `bash scripts/build_interfaces.sh` and `source scripts/env.sh`)"
        ) from None
    path = share / "msg" / f"{name}.msg"
    try:
        return path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read the definition of {package}/msg/{name}: {exc}") from exc


def _field_types(package: str, text: str) -> list[tuple[str, str]]:
    """The message types (package, name) the fields of a ``.msg`` text use, in order."""
    out: list[tuple[str, str]] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        field_type = line.split()[0]
        base = re.sub(r"\[[^\]]*\]$", "", field_type).split("<=")[0]
        if base in PRIMITIVES:
            continue
        if "/" in base:
            dep = split_type(base)
        elif base == "Header":
            dep = ("std_msgs", "Header")
        else:
            dep = (package, base)
        if dep not in out:
            out.append(dep)
    return out


@cache
def message_definition(type_name: str) -> str:
    """The full ``ros2msg`` schema text of ``type_name`` (``pkg/msg/Type``): its ``.msg`` text,
    then each type it uses (depth first, each once) after a separator and ``MSG: pkg/Type``."""
    package, name = split_type(type_name)
    main = msg_file_text(package, name)
    seen: list[tuple[str, str]] = []
    stack = list(reversed(_field_types(package, main)))
    while stack:
        dep = stack.pop()
        if dep in seen or dep == (package, name):
            continue
        seen.append(dep)
        stack.extend(reversed(_field_types(dep[0], msg_file_text(*dep))))
    parts = [main.rstrip("\n") + "\n"]
    for dep_pkg, dep_name in seen:
        text = msg_file_text(dep_pkg, dep_name).rstrip("\n")
        parts.append(f"{_SEPARATOR}\nMSG: {dep_pkg}/{dep_name}\n{text}\n")
    return "".join(parts)


def message_class(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type`` (its generated ``pkg.msg`` module)."""
    package, name = split_type(type_name)
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import {package}.msg.{name}: {exc}") from exc


def qos_yaml(qos) -> str:
    """rosbag2's ``offered_qos_profiles`` text (a YAML list of one profile) for an rclpy QoSProfile."""
    def name(policy) -> str:
        return policy.name.lower()

    never = "{sec: 9223372036, nsec: 854775807}"
    return (
        f"- history: {name(qos.history)}\n  depth: {int(qos.depth)}\n"
        f"  reliability: {name(qos.reliability)}\n  durability: {name(qos.durability)}\n"
        f"  deadline: {never}\n  lifespan: {never}\n  liveliness: automatic\n"
        f"  liveliness_lease_duration: {never}\n  avoid_ros_namespace_conventions: false\n"
    )


class McapRecording:
    """An MCAP file being written in rosbag2's layout (see the module docstring).

    ``write(topic, type_name, data)`` records one CDR message; the channel (and the type's schema)
    is added on first use. ``close()`` finishes the file (its summary and index); a file not
    closed has no index, which readers may refuse.
    """

    def __init__(self, output: str | Path | IO[bytes], compression: str = "zstd") -> None:
        self._own = not hasattr(output, "write")
        self._stream = open(output, "wb") if self._own else output  # noqa: SIM115 - closed in close()
        kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in kind:
            raise ValueError(f"compression must be one of {sorted(kind)}, got {compression!r}")
        self._writer = Writer(self._stream, compression=kind[compression])
        self._writer.start(profile="ros2", library="medc-record")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.bytes = 0
        self.closed = False
        #: Why the file stopped taking messages (None: it did not).
        self.failed: str | None = None

    def add_topic(self, topic: str, type_name: str, qos=None) -> None:
        """Declare ``topic`` of ``type_name`` (its schema text from the installed ``.msg`` files)."""
        if topic in self._channels:
            return
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                type_name, "ros2msg", message_definition(type_name).encode()
            )
        metadata = {"offered_qos_profiles": qos_yaml(qos)} if qos is not None else {}
        self._channels[topic] = self._writer.register_channel(
            topic, "cdr", self._schemas[type_name], metadata
        )
        self._sequence[topic] = 0
        self.counts[topic] = 0

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Record the CDR bytes of one message on a declared ``topic``. A write the file refuses
        (a full disk) ends the recording: ``failed`` says why, later messages are not written."""
        if self.failed is not None:
            return
        now = time.time_ns() if log_time_ns is None else log_time_ns
        self._sequence[topic] += 1
        try:
            self._writer.add_message(self._channels[topic], log_time=now, data=data, publish_time=now,
                                     sequence=self._sequence[topic])
        except OSError as exc:
            self.failed = exc.strerror or str(exc)
            return
        self.counts[topic] += 1
        self.bytes += len(data)

    def flush(self) -> None:
        """Write what is buffered to the file (an error of the file raises OSError)."""
        self._stream.flush()

    def close(self) -> None:
        """Finish the file (idempotent); a recording that ``failed`` is left as it is."""
        if self.closed:
            return
        self.closed = True
        if self.failed is None:
            try:
                self._writer.finish()
            except OSError as exc:
                self.failed = exc.strerror or str(exc)
        if self._own:
            self._stream.close()
