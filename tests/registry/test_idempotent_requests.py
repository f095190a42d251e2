"""Paid requests end to end: a lost answer or a node restart never pays or allocates twice; every
chain call has one total deadline; amounts the CLI cannot pay say what is allowed.

The faults: a proxy in front of anvil (``registry_helpers.RpcProxy``) that forwards a JSON-RPC
request and then drops the node's answer (the transaction is mined, the client never hears of it),
or drops the request itself (the node never sees the transaction), and a server built here that
accepts connections and never answers.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest
from medc_registry import ChainClient
from medc_registry.chain import ChainError
from medc_registry.cli import main as cli_main
from medc_registry.home import PENDING_FILE
from medc_registry.nodes import free_port, start_anvil
from registry_helpers import APP, PRICE, REQUEST, RpcProxy, cli_home, ledger

SEND = {"eth_sendRawTransaction"}
#: What a loaded machine may add to a deadline before the failure shows: scheduling, not waiting (a
#: request to a node that never answers would otherwise wait for its 30 s read timeout).
LATE_S = 3.0
#: What a client uses to learn a transaction's fate (dropping them all = a lost receipt).
ANSWERS = {"eth_sendRawTransaction", "eth_getTransactionReceipt", "eth_getTransactionByHash"}


@pytest.fixture
def node(tmp_path):
    """(anvil on a fixed port with a state file, restart(), proxy in front of it)."""
    port, state = free_port(), tmp_path / "anvil-state.json"
    nodes = [start_anvil(tmp_path / "n0", state_file=state, port=port)]

    def restart():
        nodes[-1].stop()  # anvil writes its state on SIGTERM
        nodes.append(start_anvil(tmp_path / f"n{len(nodes)}", state_file=state, port=port))

    proxy = RpcProxy(nodes[0].url)
    yield nodes[0], restart, proxy
    proxy.close()
    nodes[-1].stop()


def _setup(tmp_path, anvil, proxy, capsys):
    """A CLI home on the proxy: accounts 1 (owner, one model at 0.001 ETH) and 2 (requester)."""
    return cli_home(tmp_path, anvil.extra["private_keys"][:3], proxy.url, capsys)


@pytest.mark.timing
@pytest.mark.anvil
def test_lost_receipt_then_node_restart_pays_and_allocates_once(node, tmp_path, capsys):
    anvil, restart, proxy = node
    home, models = _setup(tmp_path, anvil, proxy, capsys)
    keys = anvil.extra["private_keys"][:3]
    proxy.lose_answer = set(ANSWERS)  # the payment is mined; no answer about it comes back
    started = time.monotonic()
    assert cli_main(["--deadline", "6", *home, *REQUEST]) == 2
    err = capsys.readouterr().err
    assert time.monotonic() - started < 15
    assert "not confirmed" in err and "run the same request again" in err and "cannot pay twice" in err
    assert "eth_sendRawTransaction" in proxy.seen
    assert ledger(anvil.url, keys, models) == (1, PRICE)  # it was paid, once
    pending = json.loads((tmp_path / "home" / PENDING_FILE).read_text())
    assert len(pending) == 1  # recorded before sending
    restart()
    proxy.lose_answer = set()
    assert cli_main([*home, *REQUEST]) == 0
    out = capsys.readouterr().out
    assert out.startswith("already paid: request 0x") and "nothing was paid again" in out
    assert "1 model(s) allocated" in out
    assert ledger(anvil.url, keys, models) == (1, PRICE)  # still one allocation, one payment
    records = json.loads((tmp_path / "home" / PENDING_FILE).read_text()).values()
    assert [sorted(r) for r in records] == [["account", "created", "done", "fingerprint", "request_id"]]
    # The request id itself is refused twice too.
    rid = out.split("request ")[1].split(" ")[0]
    assert cli_main([*home, *REQUEST, "--request-id", rid]) == 0
    assert capsys.readouterr().out.startswith("already paid")
    assert ledger(anvil.url, keys, models) == (1, PRICE)


@pytest.mark.timing
@pytest.mark.anvil
def test_payment_that_never_reached_the_node_is_sent_again_once(node, tmp_path, capsys):
    anvil, restart, proxy = node
    home, models = _setup(tmp_path, anvil, proxy, capsys)
    keys = anvil.extra["private_keys"][:3]
    proxy.lose_request = set(SEND)
    assert cli_main(["--deadline", "5", *home, *REQUEST]) == 2
    assert "run the same request again" in capsys.readouterr().err
    assert ledger(anvil.url, keys, models) == (0, 0)
    restart()  # the node never saw it: the transaction is unknown after the restart
    proxy.lose_request = set()
    assert cli_main([*home, *REQUEST]) == 0
    out = capsys.readouterr().out
    assert "already paid" not in out and "1 model(s) allocated" in out
    assert ledger(anvil.url, keys, models) == (1, PRICE)
    assert cli_main([*home, *REQUEST]) == 0  # a new request after a confirmed one is a new payment
    assert ledger(anvil.url, keys, models) == (2, 2 * PRICE)


@pytest.mark.timing
@pytest.mark.anvil
def test_a_stale_record_is_signed_again_with_the_same_id_and_paid_once(node, tmp_path):
    """A pending record whose transaction is unknown and whose nonce went to another transaction
    (e.g. the node lost it and the account sent something else): the same request id is signed
    again; the contract pays it once, and a further replay is refused."""
    from medc_registry import LocalContentStore, Registry, deploy_contracts

    anvil, _restart, _proxy = node
    chain = ChainClient.connect(anvil.url, anvil.extra["private_keys"])
    reg = Registry(chain, LocalContentStore(tmp_path / "s"), deploy_contracts(chain))
    owner, requester = reg.as_user(1), reg.as_user(2)
    owner.register_user()
    requester.register_user()  # uses nonce 0 of the requester
    owner.share_model(b"m", APP, {"agents": 1, "walls": 1}, PRICE)
    rid = "0x" + "07" * 32
    requester.pending.put(
        {
            "request_id": rid,
            "account": requester.address,
            "fingerprint": "what a crashed run left",
            "args": [APP, [1, 1], [], 1, 0, 0, [0]],
            "value": PRICE,
            "tx_hash": "0x" + "ab" * 32,  # never seen by the node
            "raw": "0x00",
            "nonce": 0,
            "created": 0,
        }
    )
    allocs = requester.request_models(APP, {"agents": 1, "walls": 1}, request_id=rid)
    assert not allocs[0].replayed and allocs[0].request_id == rid
    assert requester.pending_requests() == []
    again = requester.request_models(APP, {"agents": 1, "walls": 1}, request_id=rid)
    assert again[0].replayed and again[0].allocation_id == allocs[0].allocation_id
    assert reg.owed(owner.address) == PRICE and chain.call(reg.models.functions.allocationCount()) == 1


# ----------------------------------------------------------------------------- deadlines
@pytest.fixture
def silent_node():
    """A TCP server that accepts connections and never answers."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept():
        sock.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(sock.accept()[0])
            except OSError:
                continue

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    stop.set()
    t.join()
    for s in held:
        s.close()
    sock.close()


@pytest.mark.timing
def test_a_node_that_never_answers_fails_at_the_deadline(silent_node, tmp_path, capsys):
    started = time.monotonic()
    with pytest.raises(ChainError, match=r"within the 1\.5 s deadline"):
        ChainClient.connect(silent_node, ["0x" + "11" * 32], deadline=1.5)
    assert time.monotonic() - started < 1.5 + LATE_S
    home = tmp_path / "home"
    home.mkdir()
    (home / "keys.txt").write_text("0x" + "11" * 32 + "\n")
    state = {"rpc_url": silent_node, "poa": False, "key_file": str(home / "keys.txt")}
    state |= {"users_manager": "0x" + "22" * 20, "models_manager": "0x" + "33" * 20}
    (home / "registry.json").write_text(json.dumps(state))
    started = time.monotonic()
    assert cli_main(["--home", str(home), "--deadline", "2", "status"]) == 2
    assert time.monotonic() - started < 2 + LATE_S
    assert "within the 2 s deadline" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["--deadline", "inf", "status"])
    assert "positive, finite number of seconds" in capsys.readouterr().err


# ----------------------------------------------------------------------------- amounts
@pytest.mark.timing
@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "Infinity", "1e40", "-1", "0.1234567890123456789"])
@pytest.mark.parametrize("option", ["--price", "--payment"])
def test_amounts_that_cannot_be_paid_say_what_is_allowed(value, option, tmp_path, capsys):
    model = tmp_path / "m.bin"
    model.write_bytes(b"m")
    if option == "--price":
        argv = ["share", str(model), "--application", APP, "--env", "agents=1", f"--price={value}"]
    else:
        argv = ["request", "--application", APP, "--env", "agents=1", f"--payment={value}"]
    assert cli_main(["--home", str(tmp_path / "none"), *argv]) == 2
    err = capsys.readouterr().err
    assert f"{option} {value.lower()!r}" in err and "finite, non-negative number of ETH" in err
    assert "Traceback" not in err and "no registry configured" not in err
