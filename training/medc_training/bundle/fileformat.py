"""The hardened reader under every bundle: bounded reads, strict JSON within limits, the
safetensors header and tensor table checked before any tensor is decoded, atomic writes.

Nothing here knows what a manifest means (``medc_training.bundle.manifest`` does); messages never
echo the file's bytes.
"""

from __future__ import annotations

import contextlib
import math
import os
import stat
import struct
import tempfile
from pathlib import Path
from typing import Any

from medc_training import untrusted
from medc_training.nets import safe_repr
from medc_training.untrusted import (  # noqa: F401  (re-exported)
    MAX_BUNDLE_BYTES,
    MAX_JSON_DEPTH,
    MAX_NUMBER_CHARS,
    MAX_STRING_CHARS,
    json_depth,
    printable,
)

MANIFEST_KEY = "medc.manifest"

MAX_HEADER_BYTES = 1 << 20  # the manifest and tensor table of any sane bundle fit easily in 1 MiB
# Limits on the JSON of the header and of the manifest, checked before and while parsing it. The
# shipped bundles' manifests are under 2 KB, nest 4 levels deep and hold no string over 120
# characters; a 256-layer architecture needs ~25 KB.
# MAX_JSON_DEPTH, MAX_STRING_CHARS and MAX_NUMBER_CHARS are medc_training.untrusted's.
MAX_MANIFEST_CHARS = 64 << 10
_DTYPE_SIZES = {"F32": 4}


class BundleError(ValueError):
    """The file or bytes are not a valid MEDC policy bundle; the message says what is wrong."""


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _atomic_write(target: Path, data: bytes) -> None:
    # A killed writer must never leave a half-written model where a reader (or resume) looks.
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        # mkstemp makes the file 0600; a bundle is a file to share: the mode open() would give it
        # (0666 less the umask, 0644 usually).
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _where(source: Any) -> str:
    if isinstance(source, bytes | bytearray | memoryview):
        return "bundle bytes"
    return printable(os.fspath(source), 200) if isinstance(source, str | os.PathLike) else "bundle"


class _Source:
    """Bounded reads from a path or from bytes: the header is checked before the rest is read."""

    def __init__(self, source: Any) -> None:
        self.fd: int | None = None
        if isinstance(source, bytes | bytearray | memoryview):
            self.data: bytes | None = bytes(source)
            self.size = len(self.data)
            self.where = "bundle bytes"
            return
        if not isinstance(source, str | os.PathLike):
            raise TypeError(f"expected a path or bytes, got {type(source).__name__}")
        path = Path(source)
        self.where = printable(str(path), 200)
        self.data = None
        try:
            if not path.is_file():  # before opening: opening a FIFO or a device could block
                if path.is_dir():
                    raise BundleError(f"{self.where}: is a directory, not a bundle file")
                if not path.exists():
                    raise BundleError(f"{self.where}: no such file")
                raise BundleError(f"{self.where}: not a regular file")
            self.fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
            st = os.fstat(self.fd)
        except FileNotFoundError:
            self.close()
            raise BundleError(f"{self.where}: no such file") from None
        except OSError as exc:
            self.close()
            raise BundleError(f"{self.where}: cannot read: {exc.strerror or type(exc).__name__}") from None
        except BundleError:
            self.close()
            raise
        if not stat.S_ISREG(st.st_mode):
            self.close()
            raise BundleError(f"{self.where}: not a regular file")
        self.size = st.st_size
        if self.size > MAX_BUNDLE_BYTES:
            self.close()
            raise BundleError(f"{self.where}: {self.size} bytes is larger than the {MAX_BUNDLE_BYTES} "
                              "byte limit")

    def read(self, offset: int, count: int) -> bytes:
        """Exactly ``count`` bytes from ``offset`` (the caller checked that they exist)."""
        if self.data is not None:
            return self.data[offset:offset + count]
        chunks, done = [], 0
        try:
            while done < count:
                chunk = os.pread(self.fd, min(count - done, 16 << 20), offset + done)
                if not chunk:
                    break
                chunks.append(chunk)
                done += len(chunk)
        except OSError as exc:
            raise BundleError(f"{self.where}: cannot read: {exc.strerror or type(exc).__name__}") from None
        out = b"".join(chunks)
        if len(out) != count:
            raise BundleError(f"{self.where}: the file changed while it was read")
        return out

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> _Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def parse_json(text: str, what: str, max_chars: int, max_string: int = MAX_STRING_CHARS) -> Any:
    """``text`` parsed as strict JSON within this module's limits; ``BundleError`` names ``what``.

    The one bounded reader of :mod:`medc_training.untrusted` (also what the registry bridge uses
    for JSON from the graph): refused, and never echoed, are more than ``max_chars`` characters,
    nesting deeper than ``MAX_JSON_DEPTH`` (checked before parsing, so the parser never recurses
    deep), NaN/Infinity, numbers over ``MAX_NUMBER_CHARS`` characters or beyond float range,
    duplicate keys, strings or keys over ``max_string`` characters, and invalid Unicode.
    """
    try:
        return untrusted.parse_json(text, what, max_chars, max_string=max_string)
    except untrusted.UntrustedJSONError as exc:
        raise BundleError(str(exc)) from None


def _parse_header(src: _Source) -> tuple[dict[str, Any], dict[str, Any], int]:
    """Check the safetensors container; return (manifest JSON, tensor table, data start).

    Reads the 8-byte length prefix, then the header, nothing more. Messages never echo the file:
    not the prefix's value, not a byte, not a snippet of the header.
    """
    where = src.where
    if src.size < 8:
        raise BundleError(f"{where}: {src.size} bytes is too short to be a safetensors file")
    (header_len,) = struct.unpack("<Q", src.read(0, 8))
    if header_len > MAX_HEADER_BYTES:
        raise BundleError(f"{where}: the header length in the first 8 bytes is over the {MAX_HEADER_BYTES} "
                          "byte limit (not a bundle, or corrupted)")
    if 8 + header_len > src.size:
        raise BundleError(f"{where}: truncated: header needs more bytes than the file's {src.size}")
    raw = src.read(8, header_len)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise BundleError(f"{where}: header is not valid JSON (not UTF-8 text); "
                          "not a safetensors file") from None
    try:
        # The header's strings are tensor names, dtypes and the manifest (checked on its own below).
        header = parse_json(text, "header", MAX_HEADER_BYTES, max_string=MAX_HEADER_BYTES)
    except BundleError as exc:
        raise BundleError(f"{where}: {exc}; not a safetensors file") from None
    if not isinstance(header, dict):
        raise BundleError(f"{where}: header must be a JSON object")
    meta = header.pop("__metadata__", None)
    if not isinstance(meta, dict) or MANIFEST_KEY not in meta:
        raise BundleError(f"{where}: no '{MANIFEST_KEY}' in the safetensors metadata: "
                          "a safetensors file, but not a MEDC policy bundle")
    if not isinstance(meta[MANIFEST_KEY], str):
        raise BundleError(f"{where}: metadata '{MANIFEST_KEY}' must be a JSON string")
    try:
        manifest = parse_json(meta[MANIFEST_KEY], "manifest", MAX_MANIFEST_CHARS)
    except BundleError as exc:
        raise BundleError(f"{where}: {exc}") from None
    return manifest, header, 8 + header_len


def _check_table(table: dict[str, Any], data_len: int, where: str) -> None:
    """Each entry is F32 with a shape whose size matches its byte range; ranges tile the data exactly."""
    spans = []
    for name, entry in table.items():
        label = safe_repr(name)
        if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
            raise BundleError(f"{where}: tensor {label}: entry must have dtype, shape, data_offsets")
        if entry["dtype"] not in _DTYPE_SIZES:
            raise BundleError(f"{where}: tensor {label} has dtype {safe_repr(entry['dtype'], 8)}; "
                              "bundles hold F32 only")
        shape, offsets = entry["shape"], entry["data_offsets"]
        if (not isinstance(shape, list) or len(shape) > 8
                or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)):
            raise BundleError(f"{where}: tensor {label} has an invalid shape (at most 8 non-negative "
                              "integers)")
        if (not isinstance(offsets, list) or len(offsets) != 2
                or not all(isinstance(o, int) and not isinstance(o, bool) for o in offsets)
                or not 0 <= offsets[0] <= offsets[1]):
            raise BundleError(f"{where}: tensor {label} has invalid data_offsets")
        if offsets[1] - offsets[0] != math.prod(shape) * _DTYPE_SIZES[entry["dtype"]]:
            raise BundleError(f"{where}: tensor {label}: its shape does not fit its byte range")
        spans.append((offsets[0], offsets[1], name))
    spans.sort()
    cursor = 0
    for start, end, name in spans:
        if start != cursor:
            raise BundleError(f"{where}: tensor {safe_repr(name)} data does not follow the previous "
                              "tensor (overlap or gap): corrupted file")
        cursor = end
    if cursor > data_len:
        raise BundleError(f"{where}: truncated: tensors need more data bytes than the file holds")
    if cursor < data_len:
        raise BundleError(f"{where}: unexpected bytes after the last tensor")
