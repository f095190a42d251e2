"""Files the registry writes, against planted links: the pending-requests journal, its lock, the
home's registry.json and ``fetch -o``. Each is written whole through a fresh temporary file
(never a fixed, guessable name) renamed into place, so a link is replaced and its target never
written; the lock is never opened through a link; ``fetch -o`` refuses an existing file or link
unless asked to overwrite it. The links and victims are built here."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from medc_registry.files import UnsafeFileError
from medc_registry.home import save_state
from medc_registry.journal import PendingRequests
from registry_helpers import APP, PRICE
from test_hostile_registry import KEY, json_answer, serving

RECORD = {"request_id": "0x" + "ab" * 32, "account": "0x" + "cd" * 20, "fingerprint": "f"}


def _victim(tmp_path, text: str = "precious\n"):
    victim = tmp_path / "victim.txt"
    victim.write_text(text)
    return victim


def test_the_pending_file_is_written_through_no_planted_link(tmp_path):
    victim = _victim(tmp_path, "{}")
    path = tmp_path / "pending-requests.json"
    (tmp_path / "pending-requests.json.tmp").symlink_to(victim)  # the temporary name once used
    pending = PendingRequests(path)
    pending.put(RECORD)
    assert victim.read_text() == "{}" and not path.is_symlink()
    assert list(json.loads(path.read_text()).values()) == [RECORD]
    # A link at the file itself is replaced, not written through.
    path.unlink()
    path.symlink_to(victim)
    pending.put(RECORD)
    assert victim.read_text() == "{}" and not path.is_symlink() and len(pending.load()) == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp") and not p.is_symlink()] == []


def test_a_linked_lock_file_is_refused_and_nothing_is_paid(registry, users, tmp_path):
    owner, _, _, requester = users
    owner.share_model(b"one", APP, {"agents": 3, "walls": 2}, PRICE)
    victim = _victim(tmp_path)
    requester.pending = PendingRequests(tmp_path / "pending-requests.json")
    (tmp_path / "pending-requests.json.lock").symlink_to(victim)
    made = registry.chain.call(registry.models.functions.allocationCount())
    with pytest.raises(UnsafeFileError, match="is a symlink"):
        requester.request_models(APP, {"agents": 3, "walls": 2})
    assert registry.chain.call(registry.models.functions.allocationCount()) == made
    assert victim.read_text() == "precious\n"


def test_registry_json_is_written_through_no_planted_link(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    victim = _victim(tmp_path)
    (home / "registry.json.tmp").symlink_to(victim)
    save_state(home, {"rpc_url": "http://127.0.0.1:8545"})
    assert victim.read_text() == "precious\n"
    (home / "registry.json").unlink()
    (home / "registry.json").symlink_to(victim)
    save_state(home, {"rpc_url": "http://127.0.0.1:8545"})
    assert victim.read_text() == "precious\n" and not (home / "registry.json").is_symlink()
    assert json.loads((home / "registry.json").read_text()) == {"rpc_url": "http://127.0.0.1:8545"}


def test_fetch_to_refuses_an_existing_file_or_link_unless_asked(tmp_path):
    from medc_registry.content import ContentStoreError, LocalContentStore

    store = LocalContentStore(tmp_path / "store")
    cid = store.add(b"model bytes")
    out = tmp_path / "model.bin"
    assert store.fetch_to(cid, out, overwrite=False) == len(b"model bytes")
    with pytest.raises(ContentStoreError, match="exists: not overwritten"):
        store.fetch_to(cid, out, overwrite=False)
    victim = _victim(tmp_path)
    link = tmp_path / "link.bin"
    link.symlink_to(victim)
    with pytest.raises(ContentStoreError, match="exists: not overwritten"):
        store.fetch_to(cid, link, overwrite=False)
    dangling = tmp_path / "dangling.bin"
    dangling.symlink_to(tmp_path / "nowhere")
    with pytest.raises(ContentStoreError, match="exists: not overwritten"):
        store.fetch_to(cid, dangling, overwrite=False)
    assert not (tmp_path / "nowhere").exists()
    # Asked to overwrite: the link is replaced by the file, its target untouched.
    store.fetch_to(cid, link, overwrite=True)
    assert victim.read_text() == "precious\n"
    assert not link.is_symlink() and link.read_bytes() == b"model bytes"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".medc-fetch-")] == []


def _chain(conn, path, body, stop):
    """A JSON-RPC node that knows a chain id and has code everywhere (enough to open a home)."""
    request = json.loads(body)
    result = {"eth_chainId": "0x7a69", "eth_getCode": "0x6080"}.get(request["method"], "0x")
    conn.sendall(json_answer({"jsonrpc": "2.0", "id": request["id"], "result": result}))


def test_medc_registry_fetch_refuses_an_existing_output_unless_overwrite(tmp_path):
    from medc_registry.content import LocalContentStore

    cid = LocalContentStore(tmp_path / "store").add(b"model bytes")
    out = tmp_path / "model.bin"
    out.write_text("mine")
    with serving(_chain) as url:
        home = tmp_path / "home"
        home.mkdir()
        (home / "keys.txt").write_text(KEY + "\n")
        (home / "registry.json").write_text(json.dumps({
            "rpc_url": url, "poa": False, "key_file": str(home / "keys.txt"),
            "users_manager": "0x" + "22" * 20, "models_manager": "0x" + "33" * 20,
            "content": {"kind": "local", "root": str(tmp_path / "store")}}))

        def fetch(*extra: str) -> subprocess.CompletedProcess:
            argv = ["--home", str(home), "fetch", cid, "-o", str(out), *extra]
            return subprocess.run([sys.executable, "-m", "medc_registry.cli", *argv], capture_output=True,
                                  text=True, timeout=120, env=dict(os.environ))

        done = fetch()
        assert done.returncode == 2 and "exists: not overwritten" in done.stderr
        assert "--overwrite" in done.stderr
        assert "Traceback" not in done.stderr and out.read_text() == "mine"
        done = fetch("--overwrite")
        assert done.returncode == 0, done.stderr
    assert out.read_bytes() == b"model bytes"


def test_fetch_to_refuses_a_device_or_fifo_even_when_asked_to_overwrite(tmp_path):
    """``fetch -o /dev/full --overwrite`` would rename a file over the device node (as root, it
    could); a device or FIFO is refused before anything is fetched, and left as it was."""
    from medc_registry.content import ContentStoreError, LocalContentStore

    store = LocalContentStore(tmp_path / "store")
    cid = store.add(b"model bytes")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    before = os.stat("/dev/full")
    for target in ("/dev/full", fifo):
        with pytest.raises(ContentStoreError, match="is not a regular file"):
            store.fetch_to(cid, target, overwrite=True)
    after = os.stat("/dev/full")
    assert (after.st_ino, after.st_rdev) == (before.st_ino, before.st_rdev)
    assert {p.name for p in tmp_path.iterdir()} == {"store", "fifo"}
