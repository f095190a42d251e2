"""Fetches are bounded: size (declared and streamed), one total deadline, streaming verification,
DAGs that declare or assemble too much, and CID texts capped before parsing.

A fake Kubo RPC node is built here (a loopback HTTP server whose ``cat`` and ``block/get`` answers
each test scripts), with hostile answers: a 1-byte drip, an endless body, a lying length, and a DAG
whose few unique blocks link each other over and over.
"""

from __future__ import annotations

import hashlib
import threading
import time
import tracemalloc
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import pytest
from medc_registry.cid import (
    _DAG_PB,
    _RAW,
    MAX_CID_LENGTH,
    MAX_CONTENT_BYTES,
    Cid,
    CidError,
    ContentTooLargeError,
    _cid_bytes,
    _pb_node,
    _unixfs_data,
    assemble,
    compute_cid,
    iter_blocks,
    parse_cid,
)
from medc_registry.content import (
    ContentIntegrityError,
    ContentNotFoundError,
    ContentSizeError,
    ContentStoreError,
    KuboContentStore,
    LocalContentStore,
)

#: What a loaded machine may add to a deadline before the failure shows: scheduling, not waiting.
#: The hostile servers below would hold a fetch far longer (a minute) than deadline + LATE_S.
LATE_S = 3.0


class FakeKubo:
    """``answers[path](arg)`` returns (headers, iterable of body pieces, seconds between pieces)."""

    def __init__(self) -> None:
        self.answers: dict = {}
        self.calls: list[tuple[str, str]] = []
        fake = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"  # a body ends when the connection closes

            def log_message(self, *args):
                pass

            def do_POST(self):
                url = urlsplit(self.path)
                arg = parse_qs(url.query).get("arg", [""])[0]
                fake.calls.append((url.path, arg))
                headers, pieces, delay = fake.answers[url.path](arg)
                self.send_response(200)
                for key, value in headers.items():
                    self.send_header(key, value)
                self.end_headers()
                try:
                    for piece in pieces:
                        self.wfile.write(piece)
                        self.wfile.flush()
                        if delay:
                            time.sleep(delay)
                except OSError:
                    pass  # the client gave up

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def kubo():
    fake = FakeKubo()
    yield fake
    fake.close()


def _blocks(data: bytes, version: int = 0) -> dict[str, bytes]:
    return {cid.encode(): block for cid, block in iter_blocks(data, version)}


# ----------------------------------------------------------------------------- limits are consistent
def test_content_limit_is_the_bundle_loaders_ceiling(tmp_path):
    from medc_training.bundle import MAX_BUNDLE_BYTES

    assert MAX_CONTENT_BYTES == MAX_BUNDLE_BYTES
    assert LocalContentStore(tmp_path).max_size == MAX_CONTENT_BYTES
    assert KuboContentStore("http://127.0.0.1:1").max_size == MAX_CONTENT_BYTES


# ----------------------------------------------------------------------------- CID texts
@pytest.mark.parametrize("prefix", ["z", "b", "Qm", "x"])
def test_a_huge_cid_text_is_refused_instantly(prefix, tmp_path, monkeypatch):
    """Refused on its length, before any decoding (its quadratic base58 decoding took 13.6 s)."""
    from medc_registry import cid as cid_mod

    def never(text):
        raise AssertionError(f"decoded a {len(text)}-character text")

    monkeypatch.setattr(cid_mod, "b58decode", never)
    monkeypatch.setattr(cid_mod, "_b32decode", never)
    text = prefix + "1" * 200_000
    with pytest.raises(CidError, match=f"at most {MAX_CID_LENGTH} characters"):
        parse_cid(text)
    local, kubo = LocalContentStore(tmp_path), KuboContentStore("http://127.0.0.1:1")
    with pytest.raises(ContentStoreError, match="invalid CID"):
        local.fetch(text)
    with pytest.raises(ContentStoreError, match="invalid CID"):
        kubo.fetch(text)  # refused before any request (nothing listens on port 1)


# ----------------------------------------------------------------------------- deadline
@pytest.mark.timing
def test_a_dripping_node_fails_at_the_fetch_deadline(kubo):
    cid = compute_cid(b"x" * 1000)
    kubo.answers["/api/v0/cat"] = lambda arg: ({}, (b"x" for _ in range(300)), 0.2)  # 5 bytes/s, 60 s
    store = KuboContentStore(kubo.url, timeout=30, deadline=1.5)
    started = time.monotonic()
    with pytest.raises(ContentNotFoundError, match=r"within the 1\.5 s fetch deadline"):
        store.fetch(cid)
    assert time.monotonic() - started < 1.5 + LATE_S


@pytest.mark.timing
def test_a_silent_node_fails_at_the_deadline_not_the_read_timeout(kubo):
    cid = compute_cid(b"y")
    kubo.answers["/api/v0/cat"] = lambda arg: ({}, (b"" for _ in range(1)), 60.0)
    store = KuboContentStore(kubo.url, timeout=30, deadline=1.0)
    started = time.monotonic()
    with pytest.raises(ContentNotFoundError, match="fetch deadline"):
        store.fetch(cid)
    assert time.monotonic() - started < 1.0 + LATE_S


# ----------------------------------------------------------------------------- size
def test_a_body_over_the_limit_is_refused_while_streaming(kubo):
    cid = compute_cid(b"z")
    kubo.answers["/api/v0/cat"] = lambda arg: ({}, (bytes(1 << 16) for _ in range(10_000)), 0)  # 655 MB
    store = KuboContentStore(kubo.url, max_size=1 << 20)
    with pytest.raises(ContentSizeError, match="over the 1048576 byte limit; refused while streaming"):
        store.fetch(cid)


def test_a_declared_length_over_the_limit_is_refused_before_reading(kubo):
    cid = compute_cid(b"z")
    kubo.answers["/api/v0/cat"] = lambda arg: ({"X-Content-Length": str(10**10)}, [b"z"], 0)
    with pytest.raises(ContentSizeError, match="refused before reading"):
        KuboContentStore(kubo.url).fetch(cid)


def test_a_local_file_over_the_limit_is_refused_before_reading(tmp_path):
    store = LocalContentStore(tmp_path, max_size=100)
    cid = store.add(b"a" * 101)
    with pytest.raises(ContentSizeError, match="refused before reading"):
        store.fetch(cid)
    assert LocalContentStore(tmp_path).fetch(cid) == b"a" * 101


# ----------------------------------------------------------------------------- DAGs
def _node(links: list[tuple[Cid, int]], filesize: int) -> tuple[Cid, bytes]:
    block = _pb_node(
        _unixfs_data(filesize, None, tuple(size for _, size in links)),
        [(_cid_bytes(c), size) for c, size in links],
    )
    return Cid(1, _DAG_PB, hashlib.sha256(block).digest()), block


def _bomb(levels: int, declared: int | None = None) -> tuple[Cid, dict[Cid, bytes]]:
    """A DAG of ``levels`` + 1 unique blocks that assembles to 4 KiB * 174**levels bytes."""
    leaf = bytes(range(256)) * 16
    cid = Cid(1, _RAW, hashlib.sha256(leaf).digest())
    blocks, size = {cid: leaf}, len(leaf)
    for level in range(levels):
        size *= 174
        top = level == levels - 1
        cid, block = _node([(cid, size // 174)] * 174, declared if top and declared is not None else size)
        blocks[cid] = block
    return cid, blocks


def test_a_dag_declaring_more_than_the_limit_is_refused_before_assembling():
    root, blocks = _bomb(3)  # 21 GB declared, 4 unique blocks
    fetched: list[Cid] = []

    def get(c):
        fetched.append(c)
        return blocks[c]

    with pytest.raises(ContentTooLargeError, match="refused before assembling"):
        assemble(root, get)
    assert fetched == [root]


def test_a_dag_assembling_more_than_it_declares_is_refused():
    root, blocks = _bomb(2, declared=10_000)  # declares 10 kB, would assemble 124 MB
    fetched: list[Cid] = []

    def get(c):
        fetched.append(c)
        return blocks[c]

    with pytest.raises(ContentTooLargeError, match="more than the 10000 bytes it declares"):
        assemble(root, get)
    # As soon as it outgrows its declaration: the root, one inner node and the three 4 KiB leaves
    # past 10 kB, not the 30,451 blocks of the whole DAG.
    assert len(fetched) <= 5, len(fetched)


def test_the_kubo_store_refuses_a_dag_bomb_through_block_get(kubo):
    root, blocks = _bomb(3)
    by_text = {c.encode(): b for c, b in blocks.items()}
    kubo.answers["/api/v0/cat"] = lambda arg: ({}, [b"not the content"], 0)
    kubo.answers["/api/v0/block/get"] = lambda arg: ({}, [by_text[arg]], 0)
    with pytest.raises(ContentSizeError, match="refused before assembling"):
        KuboContentStore(kubo.url).fetch(root.encode())


# ----------------------------------------------------------------------------- streaming verification
def test_fetch_verifies_while_streaming_without_buffering_the_file(kubo, tmp_path):
    data = bytes(range(256)) * (48 << 12)  # 48 MiB
    cid = compute_cid(data)
    kubo.answers["/api/v0/cat"] = lambda arg: (
        {},
        (data[i : i + (1 << 16)] for i in range(0, len(data), 1 << 16)),
        0,
    )
    store = KuboContentStore(kubo.url)
    tracemalloc.start()
    try:
        assert store.fetch_to(cid, tmp_path / "got.bin") == len(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, f"{peak} bytes held while fetching {len(data)}"
    assert (tmp_path / "got.bin").read_bytes() == data
    kubo.answers["/api/v0/cat"] = lambda arg: ({}, [data[:-1], b"\x00"], 0)
    kubo.answers["/api/v0/block/get"] = lambda arg: ({}, [_blocks(data)[arg]], 0)
    assert store.fetch(cid) == data  # the DAG, block by block, after a cat that did not match
    kubo.answers["/api/v0/block/get"] = lambda arg: ({}, [b"tampered"], 0)
    with pytest.raises(ContentIntegrityError):
        store.fetch(cid)
