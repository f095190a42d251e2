"""CIDs equal Kubo's `ipfs add` output; verification refuses altered bytes."""

from __future__ import annotations

import hashlib

import pytest
from medc_registry.cid import (
    CHUNK_SIZE,
    MAX_LINKS,
    Cid,
    CidError,
    ContentMismatchError,
    assemble,
    compute_cid,
    iter_blocks,
    parse_cid,
    verify,
)

# Kubo-confirmed vectors plus Kubo's well-known empty-file CIDv0.
VECTORS = [
    (b"", 1, "bafkreihdwdcefgh4dqkjv67uzcmw7ojee6xedzdetojuzjevtenxquvyku"),
    (b"hello world\n", 0, "QmT78zSuBmuS4z925WZfrqQ1qHaJ56DQaTfyMUF7F8ff5o"),
    (bytes(1_048_576), 0, "QmVkbauSDEaMP4Tkq6Epm9uW75mWm136n81YH8fGtfwdHU"),
    (b"", 0, "QmbFMke1KXqnYyBBWxB74N4c5SBnJMVAiMNRcGu6x1AwQH"),
]


@pytest.mark.parametrize(
    ("data", "version", "expected"), VECTORS, ids=["empty-v1", "hello-v0", "1MiB-v0", "empty-v0"]
)
def test_cid_equals_kubo_vector(data, version, expected):
    assert compute_cid(data, version) == expected


def test_single_chunk_v1_is_raw_leaf_of_sha256():
    data = b"x" * CHUNK_SIZE
    cid = parse_cid(compute_cid(data, 1))
    assert cid.version == 1 and cid.codec == 0x55
    assert cid.digest == hashlib.sha256(data).digest()
    assert compute_cid(data + b"y", 1).startswith("bafybei")  # two chunks: a dag-pb root


def _links(block: bytes) -> int:
    """Number of Links (field 2) at the top level of a dag-pb block."""
    pos = count = 0
    while pos < len(block):
        key = block[pos]
        pos += 1
        length = shift = 0
        while True:
            b = block[pos]
            pos += 1
            length |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                break
        count += key == 0x12
        pos += length
    return count


@pytest.mark.parametrize("version", [0, 1])
def test_multi_level_dag_is_balanced_with_at_most_174_links(version):
    leaves = MAX_LINKS + 3  # needs a second level: 174 + 3 leaves
    data = bytes(range(256)) * (leaves * CHUNK_SIZE // 256)
    blocks = list(iter_blocks(data, version))
    internal = [b for c, b in blocks if c.codec == 0x70 and _links(b) > 0]
    assert len(blocks) == leaves + 2 + 1  # leaves, two level-1 nodes, the root
    assert [_links(b) for b in internal] == [MAX_LINKS, 3, 2]
    assert blocks[-1][0].encode() == compute_cid(data, version)
    # Distinct layouts give distinct CIDs; the same bytes always the same one.
    assert compute_cid(data, 0) != compute_cid(data, 1)
    assert compute_cid(data, version) == compute_cid(bytes(data), version)


def test_parse_cid_round_trips_and_rejects_garbage():
    for _, version, text in VECTORS:
        assert parse_cid(text).encode() == text
        assert parse_cid(text).version == version
    for bad in ["", "Qm123", "xyz", "bafy!!!", "QmT78zSuBmuS4z925WZfrqQ1qHaJ56DQaTfyMUF7F8ff5O0"]:
        with pytest.raises(CidError):
            parse_cid(bad)
    with pytest.raises(ValueError, match="cid_version"):
        compute_cid(b"x", 2)


@pytest.mark.parametrize("version", [0, 1])
def test_verify_refuses_a_single_flipped_byte(version):
    data = bytearray(b"policy bundle " * 50_000)  # several chunks
    cid = compute_cid(bytes(data), version)
    assert verify(bytes(data), cid) == bytes(data)
    data[400_000] ^= 1
    with pytest.raises(ContentMismatchError, match="does not match its CID"):
        verify(bytes(data), cid)
    with pytest.raises(ContentMismatchError):
        verify(bytes(data[:-1]), cid)


@pytest.mark.parametrize("version", [0, 1])
def test_assemble_reads_any_dag_and_refuses_a_tampered_block(version):
    data = bytes(range(251)) * 5000  # 5 chunks under one root
    blocks = dict(iter_blocks(data, version))
    cid = compute_cid(data, version)
    assert assemble(cid, blocks.__getitem__) == data
    leaf = next(c for c in blocks if c.encode() != cid)
    blocks[leaf] = blocks[leaf][:-1] + bytes([blocks[leaf][-1] ^ 1])
    with pytest.raises(ContentMismatchError, match="does not match its CID"):
        assemble(cid, blocks.__getitem__)


def test_assemble_refuses_a_directory():
    # A dag-pb node whose UnixFS type is Directory (1).
    block = bytes([0x0A, 0x02, 0x08, 0x01])
    cid = Cid(0, 0x70, hashlib.sha256(block).digest())
    with pytest.raises(CidError, match="not a file"):
        assemble(cid, lambda _: block)
