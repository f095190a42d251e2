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

CHUNK_SIZE = 262_144
MAX_LINKS = 174

_SHA2_256 = 0x12
_DAG_PB = 0x70
_RAW = 0x55
_UNIXFS_FILE = 2
_B58 = "123456789ABCDEFGHJKLMNPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz"


class CidError(ValueError):
    """A CID string that cannot be parsed or is not one this module produces."""


class ContentMismatchError(ValueError):
    """Bytes whose CID differs from the one they were fetched under (tampered or wrong content)."""


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
    """Parse a CIDv0 (``Qm...``) or a base32/base58 CIDv1 using sha2-256."""
    if not isinstance(text, str) or not text:
        raise CidError("a CID must be a non-empty string")
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


def iter_blocks(data: bytes, cid_version: int = 0) -> Iterator[tuple[Cid, bytes]]:
    """Yield ``(cid, block_bytes)`` for every block of the file's DAG, root last."""
    if cid_version not in (0, 1):
        raise ValueError(f"cid_version must be 0 or 1, got {cid_version!r}")
    chunks = [data[i : i + CHUNK_SIZE] for i in range(0, len(data), CHUNK_SIZE)] or [b""]
    level: list[_Node] = []
    for chunk in chunks:
        if cid_version == 1:
            block, codec = chunk, _RAW
        else:
            block, codec = _pb_node(_unixfs_data(len(chunk), chunk), []), _DAG_PB
        node = _Node(_cid_for(block, cid_version, codec), len(chunk), len(block))
        yield node.cid, block
        level.append(node)
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
            yield node.cid, block
            parents.append(node)
        level = parents


def compute_cid(data: bytes, cid_version: int = 0) -> str:
    """The CID ``ipfs add [--cid-version=1]`` prints for a file with these bytes."""
    *_, (root, _block) = iter_blocks(data, cid_version)
    return root.encode()


def verify(data: bytes, cid: str) -> bytes:
    """Return ``data`` if it hashes to ``cid`` under Kubo's default layout, else raise.

    Raises:
        ContentMismatchError: the bytes do not match the CID (tampered or different content).
        CidError: the CID itself is malformed or of an unsupported kind.
    """
    parsed = parse_cid(cid)
    got = compute_cid(data, parsed.version)
    if parse_cid(got) != parsed:
        raise ContentMismatchError(
            f"content does not match its CID {cid} (the {len(data)} bytes received hash to {got}); "
            "refusing tampered or wrong content"
        )
    return data


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
    return Cid(1, codec, raw[pos : pos + 32])


def assemble(cid: str | Cid, get_block: Callable[[Cid], bytes], max_blocks: int = 1_000_000) -> bytes:
    """The file under ``cid``, read block by block with every block checked against its CID.

    Works for any chunking or DAG layout (not only Kubo's defaults) of a UnixFS file made of
    dag-pb and raw blocks hashed with sha2-256. ``get_block`` returns a block's bytes.

    Raises:
        ContentMismatchError: a block does not hash to the CID that links to it.
        CidError: a block is not a UnixFS file node (e.g. a directory) or is malformed.
    """
    root = parse_cid(cid) if isinstance(cid, str) else cid
    out = bytearray()
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
        if node.codec == _RAW:
            out += block
            continue
        links: list[Cid] = []
        data = b""
        for num, value in _fields(block):
            if num == 2 and isinstance(value, bytes):
                link = dict(_fields(value))
                links.append(_cid_from_bytes(link[1]))
            elif num == 1 and isinstance(value, bytes):
                data = value
        unixfs = dict(_fields(data)) if data else {}
        kind = unixfs.get(1, 0)
        if kind not in (0, _UNIXFS_FILE):
            raise CidError(f"{root.encode()} is not a file (UnixFS type {kind})")
        payload = unixfs.get(2, b"")
        out += payload if isinstance(payload, bytes) else b""
        stack.extend(reversed(links))  # depth first, left to right
    return bytes(out)
