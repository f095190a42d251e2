"""Over-long lines from outside nodes: a status line, a header line, a chunk-size line or a trailer
line over http.client's 65,536 bytes, from the chain's JSON-RPC node and from the IPFS node. Each
is a typed error that says the answer was malformed; ``medc-registry`` ends with status 2 and one
line, never a traceback. The hostile servers are built here (loopback, raw bytes)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from test_hostile_registry import KEY, json_answer, serving

LONG = 100_000
LINES = {
    "status line": b"HTTP/1.1 200 " + b"O" * LONG + b"\r\n\r\n",
    "header line": b"HTTP/1.1 200 OK\r\nX-Long: " + b"a" * LONG + b"\r\n\r\n",
    "chunk size": b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n" + b"1" * LONG + b"\r\n",
    "trailer line": (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\nT: "
                     + b"x" * LONG + b"\r\n\r\n"),
}


def _home(tmp_path, rpc_url: str, content: dict | None = None) -> str:
    home = tmp_path / "home"
    home.mkdir(parents=True)
    (home / "keys.txt").write_text(KEY + "\n")
    state = {"rpc_url": rpc_url, "poa": False, "key_file": str(home / "keys.txt"),
             "users_manager": "0x" + "22" * 20, "models_manager": "0x" + "33" * 20}
    if content is not None:
        state["content"] = content
    (home / "registry.json").write_text(json.dumps(state))
    return str(home)


def _cli(home: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "medc_registry.cli", "--home", home, "--deadline", "30",
                           *args], capture_output=True, text=True, timeout=120)


def _chain(bad: bytes, at_once: bool):
    """A JSON-RPC node: ``bad`` for every call (``at_once``), or a good chain id, some code at every
    address, and ``bad`` for anything else."""

    def answer(conn, path, body, stop):
        request = json.loads(body)
        good = {"eth_chainId": "0x7a69", "eth_getCode": "0x6080"}.get(request["method"])
        if not at_once and good:
            conn.sendall(json_answer({"jsonrpc": "2.0", "id": request["id"], "result": good}))
        else:
            conn.sendall(bad)

    return answer


@pytest.mark.timing
@pytest.mark.parametrize("line", LINES)
def test_an_over_long_line_from_the_chain_node_is_one_clear_line(line, tmp_path):
    for at_once in (True, False):  # at connection, then on a later call
        with serving(_chain(LINES[line], at_once)) as url:
            done = _cli(_home(tmp_path / str(at_once), url), "status")
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
        assert "malformed HTTP response (LineTooLong" in done.stderr and line in done.stderr, done.stderr


@pytest.mark.timing
@pytest.mark.parametrize("line", LINES)
def test_an_over_long_line_from_the_ipfs_node_is_a_typed_error(line, tmp_path):
    from medc_registry.cid import compute_cid
    from medc_registry.content import ContentStoreError, KuboContentStore

    cid = compute_cid(b"model")
    with serving(lambda conn, path, body, stop: conn.sendall(LINES[line])) as kubo:
        store = KuboContentStore(kubo, timeout=30, deadline=60)
        for action in (lambda: store.fetch(cid), lambda: store.fetch_to(cid, tmp_path / "out.bin"),
                       lambda: store.add(b"model"), lambda: store.pin(cid), store.version):
            with pytest.raises(ContentStoreError, match=rf"malformed HTTP response \(LineTooLong.*{line}"):
                action()
        assert not (tmp_path / "out.bin").exists()
        with serving(_chain(b"", at_once=False)) as chain:
            done = _cli(_home(tmp_path, chain, {"kind": "kubo", "url": kubo}), "fetch", cid, "--account", "0")
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert "malformed HTTP response (LineTooLong" in done.stderr, done.stderr
