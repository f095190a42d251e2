"""Hostile inputs against the registry, second round: JSON from the
graph and the chain, hostile JSON-RPC and IPFS nodes, other users' on-chain strings and the CLI's
own arguments and files. Every hostile message, server and file is built here; the tests are fast
(loopback servers, the embedded chain, subprocesses of a few seconds)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest


# ----------------------------------------------------------------------------- item 5: deep JSON
def _run(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout)


def test_bridge_refuses_json_nested_70000_deep_even_with_a_raised_recursion_limit(tmp_path):
    """What crashed medc-bridge (exit 139): requirements_json / weights_json nested 70,000 deep in
    a process whose recursion limit the embedded chain raised to 100,000. Run in a child process,
    so a crash shows as its exit status instead of killing the test run."""
    proc = _run(f"""
        import sys
        from medc_registry.bridge_node import BridgeError, RegistryBridge
        from medc_registry.records import description_features
        sys.setrecursionlimit(100_000)  # what py-evm does in the bridge's process
        deep = "[" * 70_000 + "]" * 70_000
        deep_object = '{{"a":' * 70_000 + "1" + "}}" * 70_000
        shallow_deep = "[" * 2000 + "]" * 2000  # within the size limit: the depth scan refuses it

        class Registry:  # never reached: the JSON is refused first
            def request_models(self, *a, **k):
                raise AssertionError("a refused request reached the registry")

        bridge = RegistryBridge(Registry(), {str(tmp_path / "cache")!r})
        for text in (deep, deep_object, shallow_deep):
            for args in ((text, ""), ('{{"agents": 3}}', text)):
                try:
                    bridge.request("target_localization", *args)
                except BridgeError as exc:
                    assert "nests deeper than 16 levels" in str(exc) or "character limit" in str(exc), exc
                    assert text is not shallow_deep or "nests deeper" in str(exc), exc
                else:
                    raise AssertionError("accepted")
            # The same text as an on-chain model description names no features, and never crashes.
            assert description_features(text) == ()
        print("refused")
    """)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.strip() == "refused"


def test_graph_json_limits_and_a_valid_request_still_parses(tmp_path):
    from medc_registry.bridge_node import BridgeError, RegistryBridge
    from medc_registry.records import description_features

    class Registry:
        def request_models(self, application, requirements, weights, **kw):
            self.seen = (requirements, weights)
            return []

    reg = Registry()
    bridge = RegistryBridge(reg, tmp_path / "cache")
    bridge.request("target_localization", '{"agents": 3, "walls": 2}', '{"agents": 0.5, "walls": 0.5}')
    assert reg.seen == ({"agents": 3, "walls": 2}, {"agents": 0.5, "walls": 0.5})
    for bad, why in (
        ('{"agents": 3, "agents": 4}', "twice"),
        ('{"agents": NaN}', "NaN"),
        ('{"agents": 1' + "0" * 100 + "}", "more than 40 characters"),
        ('{"a": "' + "x" * 5000 + '"}', "character limit"),
        ('{"\\ud800": 1}', "lone surrogate"),
        ("[1, 2]", "must be a JSON object"),
    ):
        with pytest.raises(BridgeError, match=why):
            bridge.request("target_localization", bad)
    assert description_features('{"features": ["agents", "walls"]}') == ("agents", "walls")
    assert description_features('{"features": [1, 2]}') == ()
    assert description_features('{"features": "agents"}') == ()


# ----------------------------------------------------------------------------- hostile servers
class ScriptedServer:
    """A loopback HTTP server whose every answer is written by ``answer(sock, path, body, stop)``:
    raw bytes, at any pace (dripping header or body bytes, endless bodies, malformed JSON)."""

    def __init__(self, answer) -> None:
        self.answer = answer
        self.stop = threading.Event()
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.sock.settimeout(0.2)
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            threading.Thread(target=self._handle, args=(conn,), daemon=True).start()

    def _handle(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(5)
            data = b""
            while b"\r\n\r\n" not in data:
                data += conn.recv(65536)
            head, body = data.split(b"\r\n\r\n", 1)
            length = 0
            for line in head.split(b"\r\n")[1:]:
                name, _, value = line.partition(b":")
                if name.strip().lower() == b"content-length":
                    length = int(value)
            while len(body) < length:
                body += conn.recv(65536)
            path = head.split(b" ")[1].decode()
            self.answer(conn, path, body, self.stop)
        except OSError:
            pass
        finally:
            conn.close()

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.sock.close()


def drip(conn: socket.socket, head: bytes, byte: bytes, stop: threading.Event, every: float = 0.05) -> None:
    """Send ``head``, then ``byte`` every ``every`` seconds until the client hangs up."""
    conn.sendall(head)
    while not stop.is_set():
        conn.sendall(byte)
        time.sleep(every)


def json_answer(payload: object) -> bytes:
    body = json.dumps(payload).encode()
    return b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (
        len(body), body)


@contextlib.contextmanager
def serving(answer):
    server = ScriptedServer(answer)
    try:
        yield server.url
    finally:
        server.close()


#: What a loaded machine may add to a deadline before the failure shows: scheduling, not waiting.
#: The hostile servers here drip for ever, and the per-read timeouts are far longer than LATE_S.
LATE_S = 3.0
DRIP_HEADER = b"HTTP/1.1 200 OK\r\nX-Drip: "  # then one header byte at a time, never ending
DRIP_BODY = b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 1000000\r\n\r\n{"
KEY = "0x" + "11" * 32


# ----------------------------------------------------------------------------- item 10: deadlines
@pytest.mark.timing
@pytest.mark.parametrize("head, byte", [(DRIP_HEADER, b"a"), (DRIP_BODY, b" ")], ids=["header", "body"])
def test_a_dripping_json_rpc_node_fails_at_the_deadline(head, byte, tmp_path, capsys):
    from medc_registry import ChainClient
    from medc_registry.chain import ChainError
    from medc_registry.cli import main as cli_main

    with serving(lambda conn, path, body, stop: drip(conn, head, byte, stop)) as url:
        started = time.monotonic()
        with pytest.raises(ChainError, match=r"within the 1\.5 s deadline"):
            ChainClient.connect(url, [KEY], deadline=1.5)
        assert time.monotonic() - started < 1.5 + LATE_S
        home = tmp_path / "home"
        home.mkdir()
        (home / "keys.txt").write_text(KEY + "\n")
        state = {"rpc_url": url, "poa": False, "key_file": str(home / "keys.txt"),
                 "users_manager": "0x" + "22" * 20, "models_manager": "0x" + "33" * 20}
        (home / "registry.json").write_text(json.dumps(state))
        started = time.monotonic()
        assert cli_main(["--home", str(home), "--deadline", "2", "status"]) == 2
        assert time.monotonic() - started < 2 + LATE_S
        err = capsys.readouterr().err
        assert "within the 2 s deadline" in err and "Traceback" not in err


@pytest.mark.timing
@pytest.mark.parametrize("head, byte", [(DRIP_HEADER, b"a"), (DRIP_BODY, b" ")], ids=["header", "body"])
def test_a_dripping_ipfs_node_fails_at_the_fetch_and_add_deadlines(head, byte):
    from medc_registry.cid import compute_cid
    from medc_registry.content import ContentNotFoundError, KuboContentStore

    with serving(lambda conn, path, body, stop: drip(conn, head, byte, stop)) as url:
        store = KuboContentStore(url, timeout=1.0, deadline=2.0)
        for action in (lambda: store.fetch(compute_cid(b"model")), lambda: store.add(b"model"),
                       lambda: store.pin(compute_cid(b"model")), store.version):
            started = time.monotonic()
            with pytest.raises(ContentNotFoundError, match="within"):
                action()
            assert time.monotonic() - started < 2.0 + LATE_S


# ----------------------------------------------------------------------------- item 11: malformed answers
def _rpc(on_call):
    """A JSON-RPC node answering eth_chainId; ``on_call(conn, request)`` answers everything else."""

    def answer(conn, path, body, stop):
        request = json.loads(body)
        if request["method"] == "eth_chainId":
            conn.sendall(json_answer({"jsonrpc": "2.0", "id": request["id"], "result": "0x7a69"}))
        else:
            on_call(conn, request, stop)

    return answer


@pytest.mark.timing
def test_malformed_json_rpc_answers_are_typed_errors():
    from eth_utils import keccak
    from medc_registry import ChainClient
    from medc_registry.chain import ContractRevert, MalformedAnswer, decode_error_data

    selector = keccak(text="InsufficientPayment(uint256,uint256)")[:4]
    truncated = "0x" + (selector + bytes(10)).hex()
    cases = {
        "short eth_call result": (lambda conn, req, stop: conn.sendall(
            json_answer({"jsonrpc": "2.0", "id": req["id"], "result": "0x01"})), MalformedAnswer),
        "truncated revert data": (lambda conn, req, stop: conn.sendall(json_answer(
            {"jsonrpc": "2.0", "id": req["id"],
             "error": {"code": 3, "message": "execution reverted", "data": truncated}})), ContractRevert),
        "endless answer": (lambda conn, req, stop: drip(
            conn, b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n\r\n", b"[" * 65536, stop, 0),
            MalformedAnswer),
        "deep answer": (lambda conn, req, stop: conn.sendall(json_answer(
            json.loads("[" * 200 + "]" * 200))), MalformedAnswer),
        "10,000 headers": (lambda conn, req, stop: conn.sendall(
            b"HTTP/1.1 200 OK\r\n" + b"X-Padding: 1\r\n" * 10_000 + b"\r\n"), MalformedAnswer),
    }
    for name, (on_call, error) in cases.items():
        with serving(_rpc(on_call)) as url:
            # The answer itself is refused (its type says why), long before the deadline would end the call.
            chain = ChainClient.connect(url, [KEY], deadline=120)
            mmc = chain.contract("ModelsManager", "0x" + "33" * 20)
            started = time.monotonic()
            with pytest.raises(error) as info:
                chain.call(mmc.functions.modelCount())
            assert time.monotonic() - started < 60, name
            if error is ContractRevert:
                assert info.value.error == "MalformedRevert", name
    assert decode_error_data(selector + bytes(10)).error == "MalformedRevert"
    assert decode_error_data(bytes.fromhex("08c379a0") + bytes(7)).error == "MalformedRevert"


def _kubo(answers):
    """A Kubo RPC node: ``answers[path](conn, stop)`` for the paths it knows, 404 otherwise."""

    def answer(conn, path, body, stop):
        route = path.split("?")[0].removeprefix("/api/v0")
        if route in answers:
            answers[route](conn, stop)
        else:
            conn.sendall(b"HTTP/1.1 404 Not Found\r\nContent-Length: 9\r\n\r\nnot found")

    return answer


def _raw(body: bytes, ctype: bytes = b"text/plain"):
    return lambda conn, stop: conn.sendall(
        b"HTTP/1.1 200 OK\r\nContent-Type: %s\r\nContent-Length: %d\r\n\r\n%s" % (ctype, len(body), body))


@pytest.mark.timing
def test_malformed_ipfs_answers_are_typed_errors():
    from medc_registry.cid import Cid, _field_bytes, _unixfs_data, b58encode
    from medc_registry.content import ContentStoreError, KuboContentStore

    # A dag-pb root whose one link carries a name but no hash (it crashed assemble: KeyError).
    root = _field_bytes(2, _field_bytes(2, b"name")) + _field_bytes(1, _unixfs_data(10))
    cid = b58encode(Cid(0, 0x70, hashlib.sha256(root).digest()).multihash)
    endless = lambda conn, stop: drip(conn, b"HTTP/1.1 200 OK\r\n\r\n", b"x" * 65536, stop, 0)  # noqa: E731
    node = {"/cat": _raw(b"not the content"), "/block/get": _raw(root)}
    with serving(_kubo(node)) as url, pytest.raises(ContentStoreError, match="link without a hash"):
        KuboContentStore(url, timeout=30, deadline=120).fetch(cid)
    # Each answer is refused for what it is (the message says which), long before the deadline.
    for add_answer, why in ((_raw(b""), "answered nothing"), (endless, "byte limit"),
                            (_raw(b"{\"Name\": 1}"), "names no CID"), (_raw(b"[1"), "malformed")):
        with serving(_kubo({"/add": add_answer})) as url:
            started = time.monotonic()
            with pytest.raises(ContentStoreError, match=why):
                KuboContentStore(url, timeout=30, deadline=120).add(b"model")
            assert time.monotonic() - started < 60


# ----------------------------------------------------------------------------- item 9: price griefing
def test_an_overpriced_exact_match_cannot_block_requests_and_max_price_holds(registry, users):
    from medc_registry.chain import ContractRevert
    from registry_helpers import APP, PRICE

    owner, griefer, requester = users[0], users[1], users[2]
    near = owner.share_model(b"near", APP, {"agents": 3, "walls": 1}, PRICE)
    griefer.share_model(b"grief", APP, {"agents": 3, "walls": 2}, 2**128 - 1)  # exact, unpayable
    allocs = requester.request_models(APP, {"agents": 3, "walls": 2})
    assert [a.model_id for a in allocs] == [near.model_id] and allocs[0].price_wei == PRICE
    dear = owner.share_model(b"dear", APP, {"agents": 3, "walls": 2}, 10 * PRICE)  # exact, payable
    assert requester.quote(APP, {"agents": 3, "walls": 2})[0] == [dear.model_id]
    assert requester.quote(APP, {"agents": 3, "walls": 2}, max_price=PRICE) == ([near.model_id], PRICE)
    allocs = requester.request_models(APP, {"agents": 3, "walls": 2}, max_price=PRICE)
    assert [a.model_id for a in allocs] == [near.model_id]
    with pytest.raises(ContractRevert, match="NoEligibleModels"):
        requester.request_models(APP, {"agents": 3, "walls": 2}, max_price=PRICE - 1)
    with pytest.raises(ValueError, match="max_price"):
        requester.quote(APP, {"agents": 3, "walls": 2}, max_price=-1)


# ----------------------------------------------------------------------------- items 9, 12, 13: the CLI
EVIL_APP = "evil\x1b]0;pwned\x07\x1b[2J\x1b]8;;http://x\x1b\\"
EVIL_CID = "Qm\x1b[1A\x1b[2Kfake\x9b"


@pytest.fixture(scope="module")
def cli_home(tmp_path_factory):
    """A CLI home on anvil (local content store): account 1 shares a model at 0.001 ETH; account 3
    writes hostile records straight to the contract (no client of ours would): an application
    name and CID full of terminal escapes, escapes in feature names, and an exact match for the
    requesters' environment priced 2**128 - 1 wei."""
    from medc_registry import ChainClient
    from medc_registry.cli import main as cli_main
    from medc_registry.nodes import start_anvil
    from registry_helpers import APP

    tmp = tmp_path_factory.mktemp("cli")
    anvil = start_anvil(tmp / "anvil")
    try:
        keys = anvil.extra["private_keys"][:4]
        (tmp / "keys.txt").write_text("\n".join(keys) + "\n")
        home = ["--home", str(tmp / "home")]
        assert cli_main([*home, "deploy", "--rpc", anvil.url, "--key-file", str(tmp / "keys.txt")]) == 0
        for account in ("1", "2", "3"):
            assert cli_main([*home, "register", "--account", account]) == 0
        (tmp / "expert.bin").write_bytes(b"expert bundle")
        share = ["share", str(tmp / "expert.bin"), "--application", APP, "--env", "agents=1"]
        assert cli_main([*home, *share, "--env", "walls=3", "--price", "0.001", "--account", "1"]) == 0
        models = json.loads((tmp / "home" / "registry.json").read_text())["models_manager"]
        chain = ChainClient.connect(anvil.url, keys)
        mmc = chain.contract("ModelsManager", models)
        desc = json.dumps({"features": ["agents\x1b[31m", "walls\x07"]})
        chain.transact(mmc.functions.addModel(EVIL_APP, EVIL_CID, desc, [3, 2], 0), sender=3)
        chain.transact(mmc.functions.addModel(APP, EVIL_CID, desc, [3, 2], 2**128 - 1), sender=3)
        yield home, tmp, chain, mmc
    finally:
        anvil.stop()


def _clean(text: str) -> None:
    assert not any((ord(ch) < 32 and ch != "\n") or 127 <= ord(ch) < 160 for ch in text), repr(text)
    assert "Traceback" not in text


@pytest.mark.anvil
def test_cli_escapes_on_chain_strings_and_passes_over_unpayable_models(cli_home, capsys):
    from medc_registry.cli import main as cli_main
    from registry_helpers import APP

    home, _tmp, chain, mmc = cli_home
    assert cli_main([*home, "models"]) == 0
    out = capsys.readouterr().out
    _clean(out)
    assert "evil?]0;pwned??[2J?]8;;http://x?" in out and "Qm?[1A?[2Kfake?" in out
    assert "agents\\x1b[31m" in out  # feature names are shown as Python reprs, escapes as text
    request = ["request", "--application", APP, "--env", "agents=3", "--env", "walls=2", "--account", "2"]
    before = chain.call(mmc.functions.allocationCount())
    assert cli_main([*home, *request]) == 0  # the 2**128 - 1 wei exact match is passed over
    out = capsys.readouterr().out
    _clean(out)
    assert "1 model(s) allocated" in out and "0.001 ETH" in out
    assert cli_main([*home, *request, "--max-price", "0.0009"]) == 2
    captured = capsys.readouterr()
    _clean(captured.err)
    assert "NoEligibleModels" in captured.err
    assert cli_main([*home, *request, "--max-price", "1e999999999"]) == 2
    assert "too large" in capsys.readouterr().err
    assert chain.call(mmc.functions.allocationCount()) == before + 1


@pytest.mark.anvil
def test_cli_refuses_hostile_arguments_and_files_with_clear_errors(cli_home, capsys):
    from medc_registry.cli import main as cli_main
    from medc_registry.home import PENDING_FILE
    from registry_helpers import APP

    home, tmp, chain, mmc = cli_home
    count = chain.call(mmc.functions.modelCount())
    # Allocation ids past uint256 are refused before the ABI encoder sees them.
    assert cli_main([*home, "review", str(2**256), "0.5", "--account", "2"]) == 2
    err = capsys.readouterr().err
    _clean(err)
    assert "0 to 2**256 - 1" in err
    assert cli_main([*home, "review", str(2**256 - 1), "0.5", "--account", "2"]) == 2
    assert "UnknownAllocation" in capsys.readouterr().err
    # 100 KB descriptions and application names are refused before anything is sent.
    share = ["share", str(tmp / "expert.bin"), "--env", "agents=1", "--env", "walls=3", "--account", "1"]
    for extra in (["--application", APP, "--description", "d" * 100_000], ["--application", "a" * 100_000]):
        assert cli_main([*home, *share, *extra]) == 2
        err = capsys.readouterr().err
        _clean(err)
        assert "byte limit" in err
    assert chain.call(mmc.functions.modelCount()) == count
    # A hand-edited pending file is refused with what to do, never ignored nor a traceback.
    pending = tmp / "home" / PENDING_FILE
    saved = pending.read_text() if pending.exists() else None
    request = ["request", "--application", APP, "--env", "agents=1", "--env", "walls=3", "--account", "2"]
    try:
        for text, why in (("[]", "must hold a JSON object"), ("null", "must hold a JSON object"),
                          ('{"k": {"account": "x"}}', "no request_id"), ("{", "not valid JSON"),
                          ('{"k": {"request_id": "0x' + "1" * 64 + '", "account": "a", "fingerprint": "f", '
                           '"tx_hash": "0x12"}}', "lacks a valid tx_hash")):
            pending.write_text(text)
            assert cli_main([*home, *request]) == 2
            err = capsys.readouterr().err
            _clean(err)
            assert why in err and "restore it" in err, err
    finally:
        if saved is None:
            pending.unlink()
        else:
            pending.write_text(saved)
    # fetch -o FOLDER: refused, and no temporary file is left anywhere.
    cid = chain.call(mmc.functions.getModelText(0))[0]
    out_dir = tmp / "out"
    out_dir.mkdir()
    assert cli_main([*home, "fetch", cid, "-o", str(out_dir), "--account", "2"]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert list(out_dir.iterdir()) == [] and not list(tmp.glob(".medc-fetch-*"))
    assert cli_main([*home, "fetch", cid, "-o", str(out_dir / "m.bin"), "--account", "2"]) == 0
    assert (out_dir / "m.bin").read_bytes() == b"expert bundle"
    assert sorted(p.name for p in out_dir.iterdir()) == ["m.bin"]


@pytest.mark.parametrize("value, why", [
    ("1e999999999", "too large"), ("1e-999999999", "more than 18 decimals"),
    ("1e-19", "more than 18 decimals"), ("1" * 200, "over 100 characters"), ("-1e-999999999", "negative"),
])
def test_amounts_with_extreme_exponents_are_refused(value, why, tmp_path, capsys):
    from medc_registry.cli import main as cli_main
    from medc_registry.cli import parse_eth

    model = tmp_path / "m.bin"
    model.write_bytes(b"m")
    argv = ["share", str(model), "--application", "app", "--env", "agents=1", f"--price={value}"]
    assert cli_main(["--home", str(tmp_path / "none"), *argv]) == 2
    err = capsys.readouterr().err
    assert why in err and "Traceback" not in err
    assert parse_eth("1e-18") == 1 and parse_eth("0.001") == 10**15 and parse_eth("1E3") == 10**21
    assert parse_eth("0") == parse_eth("0e-999999999") == parse_eth("-0") == 0
    assert parse_eth("340282366920938463463.374607431768211455") == 2**128 - 1


def test_share_and_cid_read_regular_files_only(tmp_path):
    """/dev/zero was read until the kernel killed the process; a FIFO hung. Run in a child
    process, so a regression shows as a timeout, not a hung or killed test run."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    cases = [["cid", "/dev/zero"], ["cid", str(fifo)], ["cid", str(tmp_path)],
             ["share", str(fifo), "--application", "app", "--env", "agents=1"],
             ["share", "/dev/zero", "--application", "app", "--env", "agents=1"]]
    proc = _run(f"""
        from medc_registry.cli import main
        for argv in {cases!r}:
            print(main(["--home", {str(tmp_path / "h")!r}, *argv]), flush=True)
    """, timeout=180)
    assert proc.stdout.split() == ["2"] * len(cases), proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == len(cases) and all("is not a regular file" in line for line in lines), lines


def test_oversize_local_files_are_refused_before_reading(tmp_path, monkeypatch, capsys):
    from medc_registry import cli

    big = tmp_path / "big.bin"
    with open(big, "wb") as fh:
        fh.truncate(1 << 20)  # sparse: nothing is written
    monkeypatch.setattr(cli, "MAX_CONTENT_BYTES", 1000)
    assert cli.main(["cid", str(big)]) == 2
    assert "over the 1000 byte content limit" in capsys.readouterr().err
