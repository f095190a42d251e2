"""Content identifiers exactly as Kubo's ``ipfs add`` computes them for a single file.

Layout (go-unixfs importer defaults): fixed-size chunks of 262,144 bytes, a balanced DAG with at
most 174 links per node, dag-pb nodes carrying UnixFS ``Data`` messages, sha2-256 multihashes.

* CIDv0 (``ipfs add``): leaves are dag-pb UnixFS ``File`` nodes; printed in base58btc (``Qm...``).
* CIDv1 (``ipfs add --cid-version=1``): raw leaves (codec ``raw``); a one-chunk file's CID is its
  raw leaf; printed in base32 (``bafy...`` for dag-pb roots, ``bafk...`` for raw).

Only the small pieces of protobuf, multihash, multibase and CID encoding this needs are written
here; :func:`verify` recomputes the CID of fetched bytes with the layout the CID's version implies,
and :func:`assemble` reads any UnixFS file DAG block by block, checking every block's hash.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from medc_training.untrusted import MAX_BUNDLE_BYTES

CHUNK_SIZE = 262_144
MAX_LINKS = 174
#: Longest CID text accepted (a sha2-256 CID is 46-62 characters; the contract stores at most
#: 128). Checked before any decoding, so parsing is linear and instant on any input.
MAX_CID_LENGTH = 128
#: Largest content fetched or assembled: the policy bundles' ceiling
#: (:data:`medc_training.untrusted.MAX_BUNDLE_BYTES`), so nothing is fetched and cached that the
#: agents would then refuse.
MAX_CONTENT_BYTES = MAX_BUNDLE_BYTES
#: Largest single block read from a node (Kubo's bitswap limit is 2 MiB).
MAX_BLOCK_BYTES = 2 << 20

_SHA2_256 = 0x12
_DAG_PB = 0x70
_RAW = 0x55
_UNIXFS_FILE = 2
_B58 = "123456789ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz"


class CidError(ValueError):
    """A CID string that cannot be parsed or is not one this module produces."""


class ContentMismatchError(ValueError):
    """Bytes whose CID differs from the one they were fetched under (tampered or wrong content)."""


class ContentTooLargeError(ValueError):
    """Content (declared or received) over the size limit."""


# ---------------------------------------------------------------- encodings
def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _read_varint(data: bytes, pos: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        if pos >= len(data):
            raise CidError("truncated varint in CID")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7


def _field_bytes(num: int, payload: bytes) -> bytes:
    return _varint((num << 3) | 2) + _varint(len(payload)) + payload


def _field_varint(num: int, value: int) -> bytes:
    return _varint(num << 3) + _varint(value)


def b58encode(data: bytes) -> str:
    """Bitcoin base58 alphabet (multibase ``z`` without the prefix)."""
    n = int.from_bytes(data, "big")
    out = ""
    while n:
        n, r = divmod(n, 58)
        out = _B58[r] + out
    pad = len(data) - len(data.lstrip(b"\0"))
    return "1" * pad + out


def b58decode(text: str) -> bytes:
    """Inverse of :func:`b58encode`."""
    n = 0
    for ch in text:
        idx = _B58.find(ch)
        if idx < 0:
            raise CidError(f"invalid base58 character {ch!r}")
        n = n * 58 + idx
    body = n.to_bytes((n.bit_length() + 7) // 8, "big") if n else b""
    pad = len(text) - len(text.lstrip("1"))
    return b"\0" * pad + body


def _b32(data: bytes) -> str:
    return base64.b32encode(data).decode().lower().rstrip("=")


def _b32decode(text: str) -> bytes:
    try:
        return base64.b32decode(text.upper() + "=" * (-len(text) % 8))
    except ValueError as exc:
        raise CidError(f"invalid base32 CID: {exc}") from None


# ---------------------------------------------------------------- CIDs
@dataclass(frozen=True)
class Cid:
    """A parsed CID: version, content codec and sha2-256 digest."""

    version: int
    codec: int
    digest: bytes

    @property
    def multihash(self) -> bytes:
        return bytes([_SHA2_256, len(self.digest)]) + self.digest

    def encode(self) -> str:
        """Kubo's text form: base58btc for v0, multibase base32 (``b...``) for v1."""
        if self.version == 0:
            return b58encode(self.multihash)
        return "b" + _b32(_varint(1) + _varint(self.codec) + self.multihash)

    def __str__(self) -> str:
        return self.encode()


def _cid_for(block: bytes, version: int, codec: int) -> Cid:
    return Cid(version, codec, hashlib.sha256(block).digest())


def parse_cid(text: str) -> Cid:
    """Parse a CIDv0 (``Qm...``) or a base32/base58 CIDv1 using sha2-256.

    Texts longer than :data:`MAX_CID_LENGTH` are refused before any decoding.
    """
    if not isinstance(text, str) or not text:
        raise CidError("a CID must be a non-empty string")
    if len(text) > MAX_CID_LENGTH:
        raise CidError(f"a CID has at most {MAX_CID_LENGTH} characters, got {len(text)}")
    if len(text) == 46 and text.startswith("Qm"):
        mh = b58decode(text)
        if len(mh) != 34 or mh[0] != _SHA2_256 or mh[1] != 32:
            raise CidError(f"{text!r} is not a sha2-256 CIDv0")
        return Cid(0, _DAG_PB, mh[2:])
    if text[0] == "b":
        raw = _b32decode(text[1:])
    elif text[0] == "z":
        raw = b58decode(text[1:])
    else:
        raise CidError(f"unsupported CID form {text!r} (expected Qm... or base32 b... / base58 z... CIDv1)")
    version, pos = _read_varint(raw, 0)
    codec, pos = _read_varint(raw, pos)
    hash_code, pos = _read_varint(raw, pos)
    length, pos = _read_varint(raw, pos)
    digest = raw[pos:]
    if version != 1 or codec not in (_DAG_PB, _RAW):
        raise CidError(f"{text!r}: only CIDv1 with dag-pb or raw codecs is supported")
    if hash_code != _SHA2_256 or length != 32 or len(digest) != 32:
        raise CidError(f"{text!r}: only sha2-256 multihashes are supported")
    return Cid(1, codec, digest)


# ---------------------------------------------------------------- UnixFS DAG
def _unixfs_data(filesize: int, data: bytes | None = None, blocksizes: tuple[int, ...] = ()) -> bytes:
    out = _field_varint(1, _UNIXFS_FILE)
    if data:
        out += _field_bytes(2, data)
    out += _field_varint(3, filesize)
    for size in blocksizes:
        out += _field_varint(4, size)
    return out


def _pb_node(data: bytes, links: list[tuple[bytes, int]]) -> bytes:
    # dag-pb canonical form: every Link (field 2) before Data (field 1).
    out = b""
    for cid_bytes, tsize in links:
        link = _field_bytes(1, cid_bytes) + _field_bytes(2, b"") + _field_varint(3, tsize)
        out += _field_bytes(2, link)
    return out + _field_bytes(1, data)


@dataclass(frozen=True)
class _Node:
    cid: Cid
    filesize: int  # bytes of file content under this node
    tsize: int  # cumulative serialized size (block plus descendants), as Kubo's link Tsize


def _cid_bytes(cid: Cid) -> bytes:
    if cid.version == 0:
        return cid.multihash
    return _varint(1) + _varint(cid.codec) + cid.multihash


def _leaf(chunk: bytes, cid_version: int) -> tuple[_Node, bytes]:
    if cid_version == 1:
        block, codec = bytes(chunk), _RAW
    else:
        block, codec = _pb_node(_unixfs_data(len(chunk), bytes(chunk)), []), _DAG_PB
    return _Node(_cid_for(block, cid_version, codec), len(chunk), len(block)), block


def _parents(level: list[_Node], cid_version: int) -> Iterator[tuple[_Node, bytes]]:
    """The balanced DAG's inner nodes over ``level`` (the leaves), bottom up, root last."""
    while len(level) > 1:
        parents = []
        for i in range(0, len(level), MAX_LINKS):
            group = level[i : i + MAX_LINKS]
            sizes = tuple(n.filesize for n in group)
            block = _pb_node(
                _unixfs_data(sum(sizes), None, sizes), [(_cid_bytes(n.cid), n.tsize) for n in group]
            )
            node = _Node(
                _cid_for(block, cid_version, _DAG_PB), sum(sizes), len(block) + sum(n.tsize for n in group)
            )
            yield node, block
            parents.append(node)
        level = parents


def iter_blocks(data: bytes, cid_version: int = 0) -> Iterator[tuple[Cid, bytes]]:
    """Yield ``(cid, block_bytes)`` for every block of the file's DAG, root last."""
    if cid_version not in (0, 1):
        raise ValueError(f"cid_version must be 0 or 1, got {cid_version!r}")
    view = memoryview(data)
    level: list[_Node] = []
    for i in range(0, max(len(view), 1), CHUNK_SIZE):
        node, block = _leaf(view[i : i + CHUNK_SIZE], cid_version)
        yield node.cid, block
        level.append(node)
    for node, block in _parents(level, cid_version):
        yield node.cid, block


class CidBuilder:
    """Kubo's CID of a file fed in pieces (``update``), holding one chunk, not the file."""

    def __init__(self, cid_version: int = 0) -> None:
        if cid_version not in (0, 1):
            raise ValueError(f"cid_version must be 0 or 1, got {cid_version!r}")
        self.version = cid_version
        self.size = 0
        self._pending = bytearray()
        self._leaves: list[_Node] = []

    def update(self, data: bytes) -> None:
        """Feed the next bytes of the file."""
        view = memoryview(data).cast("B")
        self.size += len(view)
        if self._pending:
            need = CHUNK_SIZE - len(self._pending)
            self._pending += view[:need]
            view = view[need:]
            if len(self._pending) < CHUNK_SIZE:
                return
            self._leaves.append(_leaf(self._pending, self.version)[0])
        full = len(view) - len(view) % CHUNK_SIZE
        for i in range(0, full, CHUNK_SIZE):
            self._leaves.append(_leaf(view[i : i + CHUNK_SIZE], self.version)[0])
        self._pending = bytearray(view[full:])

    def finish(self) -> Cid:
        """The file's CID (call once, after the last ``update``)."""
        if self._pending or not self._leaves:
            self._leaves.append(_leaf(self._pending, self.version)[0])
            self._pending = bytearray()
        root = self._leaves[-1]
        for node, _block in _parents(self._leaves, self.version):
            root = node
        return root.cid


def compute_cid(data: bytes, cid_version: int = 0) -> str:
    """The CID ``ipfs add [--cid-version=1]`` prints for a file with these bytes."""
    builder = CidBuilder(cid_version)
    builder.update(data)
    return builder.finish().encode()


def verify(data: bytes, cid: str) -> bytes:
    """Return ``data`` if it hashes to ``cid`` under Kubo's default layout, else raise.

    Raises:
        ContentMismatchError: the bytes do not match the CID (tampered or different content).
        CidError: the CID itself is malformed or of an unsupported kind.
    """
    builder = CidBuilder(parse_cid(cid).version)
    builder.update(data)
    check_built(builder, cid)
    return data


def check_built(builder: CidBuilder, cid: str) -> None:
    """Raise :class:`ContentMismatchError` unless the bytes fed to ``builder`` hash to ``cid``."""
    parsed = parse_cid(cid)
    got = builder.finish()
    if got != parsed:
        raise ContentMismatchError(
            f"content does not match its CID {cid} (the {builder.size} bytes received hash to "
            f"{got.encode()}); refusing tampered or wrong content"
        )


# ---------------------------------------------------------------- reading a DAG block by block
def _fields(block: bytes) -> Iterator[tuple[int, int | bytes]]:
    """Top-level protobuf fields (number, varint value or length-delimited bytes)."""
    pos = 0
    while pos < len(block):
        key, pos = _read_varint(block, pos)
        num, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _read_varint(block, pos)
            yield num, value
        elif wire == 2:
            length, pos = _read_varint(block, pos)
            if pos + length > len(block):
                raise CidError("truncated protobuf field")
            yield num, block[pos : pos + length]
            pos += length
        else:
            raise CidError(f"unsupported protobuf wire type {wire}")


def _cid_from_bytes(raw: bytes) -> Cid:
    if len(raw) == 34 and raw[0] == _SHA2_256 and raw[1] == 32:
        return Cid(0, _DAG_PB, raw[2:])
    version, pos = _read_varint(raw, 0)
    codec, pos = _read_varint(raw, pos)
    hash_code, pos = _read_varint(raw, pos)
    length, pos = _read_varint(raw, pos)
    if version != 1 or codec not in (_DAG_PB, _RAW) or hash_code != _SHA2_256 or length != 32:
        raise CidError("link to an unsupported CID kind (only sha2-256 dag-pb/raw)")
    if len(raw) != pos + 32:
        raise CidError("link with a truncated or over-long hash")
    return Cid(1, codec, raw[pos : pos + 32])


def assemble(
    cid: str | Cid,
    get_block: Callable[[Cid], bytes],
    max_blocks: int = 1_000_000,
    max_size: int = MAX_CONTENT_BYTES,
    write: Callable[[bytes], object] | None = None,
) -> bytes:
    """The file under ``cid``, read block by block with every block checked against its CID.

    Works for any chunking or DAG layout (not only Kubo's defaults) of a UnixFS file made of
    dag-pb and raw blocks hashed with sha2-256. ``get_block`` returns a block's bytes. The root's
    declared file size must be at most ``max_size`` (checked before any other block is read),
    and the bytes assembled may never exceed it (a DAG that links the same blocks over and over
    is refused as soon as it outgrows what it declared). With ``write`` the bytes are handed to
    it as they are assembled and ``b""`` is returned.

    Raises:
        ContentMismatchError: a block does not hash to the CID that links to it.
        ContentTooLargeError: the file declares or assembles more than ``max_size`` bytes.
        CidError: a block is not a UnixFS file node (e.g. a directory) or is malformed.
    """
    root = parse_cid(cid) if isinstance(cid, str) else cid
    out = bytearray()
    sink = write or out.extend
    limit: int | None = None  # the root's declared size (raw roots: their block's length)
    total = 0
    stack = [root]
    seen = 0
    while stack:
        node = stack.pop()
        seen += 1
        if seen > max_blocks:
            raise CidError(f"DAG has more than {max_blocks} blocks")
        block = get_block(node)
        if hashlib.sha256(block).digest() != node.digest:
            raise ContentMismatchError(
                f"block {node.encode()} of {root.encode()} does not match its CID; refusing tampered content"
            )
        payload: bytes = block
        links: list[Cid] = []
        if node.codec != _RAW:
            data = b""
            for num, value in _fields(block):
                if num == 2 and isinstance(value, bytes):
                    link = dict(_fields(value))
                    target = link.get(1)
                    if not isinstance(target, bytes):
                        raise CidError(f"block {node.encode()} of {root.encode()} has a link without a hash")
                    links.append(_cid_from_bytes(target))
                elif num == 1 and isinstance(value, bytes):
                    data = value
            unixfs = dict(_fields(data)) if data else {}
            kind = unixfs.get(1, 0)
            if kind not in (0, _UNIXFS_FILE):
                raise CidError(f"{root.encode()} is not a file (UnixFS type {kind})")
            raw_payload = unixfs.get(2, b"")
            payload = raw_payload if isinstance(raw_payload, bytes) else b""
            if limit is None:
                declared = unixfs.get(3, len(payload))
                limit = declared if isinstance(declared, int) else 0
        elif limit is None:
            limit = len(block)
        if limit > max_size:
            raise ContentTooLargeError(
                f"{root.encode()} declares {limit} bytes, over the {max_size} byte limit; "
                "refused before assembling"
            )
        total += len(payload)
        if total > limit:
            raise ContentTooLargeError(
                f"{root.encode()} assembles to more than the {limit} bytes it declares; refused"
            )
        if payload:
            sink(payload)
        stack.extend(reversed(links))  # depth first, left to right
    return b"" if write else bytes(out)
