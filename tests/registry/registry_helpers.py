"""Shared constants and helpers of the registry tests (imported by name; not a test module)."""

from __future__ import annotations

import json
import threading
import time
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from medc_registry.chain import ContractRevert

APP = "target_localization"
PRICE = 10**15  # 0.001 ETH
#: The paid request the CLI tests make: account 2 asks for experts of an A3W2 requester.
REQUEST = ["request", "--application", APP, "--env", "agents=3", "--env", "walls=2", "--account", "2"]


def revert_of(excinfo: pytest.ExceptionInfo) -> ContractRevert:
    """The ContractRevert of a pytest.raises block."""
    assert isinstance(excinfo.value, ContractRevert)
    return excinfo.value


class RpcProxy:
    """A loopback HTTP proxy in front of the JSON-RPC node at ``target`` that can be made slow or
    faulty while a test runs: every call waits ``delay`` seconds first (a slow node); a call for
    whose request (the JSON-RPC object) ``hold`` is true waits until ``release`` is set (a node that
    takes as long as the test wants); methods in ``lose_request`` never reach the node; methods in
    ``lose_answer`` reach it but their answer is dropped (the transaction is mined, the client
    never hears of it). ``seen`` lists every method called, in order."""

    def __init__(self, target: str, delay: float = 0.0) -> None:
        self.target = target
        self.delay = delay
        self.hold = lambda request: False
        self.release = threading.Event()
        self.lose_answer: set[str] = set()
        self.lose_request: set[str] = set()
        self.seen: list[str] = []
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        proxy = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                request = json.loads(body)
                method = request.get("method", "")
                proxy.seen.append(method)
                if proxy.hold(request):
                    proxy.release.wait(600)
                time.sleep(proxy.delay)
                if method in proxy.lose_request:
                    self.close_connection = True
                    return
                req = urllib.request.Request(proxy.target, body, {"Content-Type": "application/json"})
                with urllib.request.urlopen(req, timeout=30) as resp:
                    answer = resp.read()
                if method in proxy.lose_answer:
                    self.close_connection = True
                    return
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(answer)))
                self.end_headers()
                self.wfile.write(answer)

        return Handler

    def close(self) -> None:
        self.release.set()
        self.server.shutdown()
        self.server.server_close()


def cli_home(tmp_path: Path, keys: list[str], rpc_url: str, capsys) -> tuple[list[str], str]:
    """A ``medc-registry`` home under ``tmp_path`` deployed through ``rpc_url`` with ``keys``:
    accounts 1 (owner of one model at PRICE) and 2 (requester) registered. Returns (the ``--home``
    argv, the Models Manager's address)."""
    from medc_registry.cli import main as cli_main

    (tmp_path / "keys.txt").write_text("\n".join(keys) + "\n")
    home = ["--home", str(tmp_path / "home")]
    assert cli_main([*home, "deploy", "--rpc", rpc_url, "--key-file", str(tmp_path / "keys.txt")]) == 0
    for account in ("1", "2"):
        assert cli_main([*home, "register", "--account", account]) == 0
    model = tmp_path / "expert.bin"
    model.write_bytes(b"expert bundle")
    share = ["share", str(model), "--application", APP, "--env", "agents=1", "--env", "walls=3"]
    assert cli_main([*home, *share, "--price", "0.001", "--account", "1"]) == 0
    capsys.readouterr()
    return home, json.loads((tmp_path / "home" / "registry.json").read_text())["models_manager"]


def ledger(url: str, keys: list[str], models: str) -> tuple[int, int]:
    """(allocations, wei owed to the owner, account 1) read straight from the node at ``url``."""
    from medc_registry import ChainClient

    chain = ChainClient.connect(url, keys)
    mmc = chain.contract("ModelsManager", models)
    return chain.call(mmc.functions.allocationCount()), chain.call(mmc.functions.owed(chain.addresses[1]))
