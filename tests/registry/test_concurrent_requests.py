"""Payments stay single when runs overlap, against anvil.

A loopback proxy in front of anvil delays every JSON-RPC call (a slow node,
``registry_helpers.RpcProxy``), and ``medc-registry request`` runs as separate processes sharing
one home: a second run started while the first still waits on the slow node, and two runs
started together. Each must end with one allocation and one payment; the later run reports the
earlier run's allocation. The proxy holds the paying run on the node, at its first read once its
request is recorded (whether that request was paid already), until the other run waits for the
pending file's lock: the runs overlap however slowly a loaded machine starts them. A held read
that times out is read again, which changes nothing.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from eth_utils import function_signature_to_4byte_selector
from medc_registry.home import PENDING_FILE
from medc_registry.nodes import start_anvil
from registry_helpers import PRICE, REQUEST, RpcProxy, cli_home, ledger

#: ModelsManager.paidRequest: what a run reads first under the pending file's lock.
PAID_REQUEST = "0x" + function_signature_to_4byte_selector("paidRequest(address,bytes32)").hex()


def _paid_request(request: dict) -> bool:
    """Whether a JSON-RPC request is an eth_call of ModelsManager.paidRequest."""
    params = request.get("params") or [{}]
    call = params[0] if isinstance(params[0], dict) else {}
    data = call.get("data") or call.get("input") or ""
    return request.get("method") == "eth_call" and data.startswith(PAID_REQUEST)


@pytest.fixture
def slow_home(tmp_path, capsys):
    """(home argv, proxy, ledger()) of a CLI home on anvil behind a delaying proxy; accounts 1
    (owner of one model at 0.001 ETH) and 2 (requester) registered."""
    anvil = start_anvil(tmp_path / "anvil")
    proxy = RpcProxy(anvil.url)
    try:
        keys = anvil.extra["private_keys"][:3]
        home, models = cli_home(tmp_path, keys, proxy.url, capsys)
        yield home, proxy, lambda: ledger(anvil.url, keys, models)
    finally:
        proxy.close()
        anvil.stop()


def _start(home: list[str]) -> subprocess.Popen:
    # A deadline longer than any hold here (the CLI's default is 30 s).
    return subprocess.Popen([sys.executable, "-m", "medc_registry.cli", "--deadline", "300", *home, *REQUEST],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))


def _finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=400)
    return proc.returncode, out, err


def _waits_for_the_lock(proc: subprocess.Popen, home: list[str]) -> bool:
    """Whether ``proc`` has the pending file's lock open: it holds it, or waits for it (a run opens it
    once its request has begun, and keeps it to the end of its request)."""
    lock, fds = str(Path(home[1]) / f"{PENDING_FILE}.lock"), Path(f"/proc/{proc.pid}/fd")
    with contextlib.suppress(OSError):
        for fd in os.listdir(fds):
            with contextlib.suppress(OSError):
                if os.readlink(fds / fd) == lock:
                    return True
    return False


def _wait_for(condition, procs: list[subprocess.Popen], what: str, timeout_s: float = 180) -> None:
    """Poll until ``condition()``; every process of ``procs`` must keep running meanwhile."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        ended = [p.communicate() for p in procs if p.poll() is not None]
        assert not ended, (what, ended)
        assert time.monotonic() < deadline, f"{what} within {timeout_s:.0f} s"
        time.sleep(0.05)


@pytest.mark.timing
@pytest.mark.anvil
@pytest.mark.slow
def test_a_second_run_during_a_slow_first_run_pays_nothing_more(slow_home):
    """With a node answering in 0.4 s per call, a second run of the same request
    started while the first still waits on the node, its request recorded (held there until the
    second waits for the first's lock), resolves the first run's request."""
    home, proxy, ledger = slow_home
    proxy.delay = 0.4
    held: list[dict] = []  # the calls held so far

    def hold(request: dict) -> bool:
        if _paid_request(request):
            held.append(request)
            return True
        return False

    proxy.hold = hold
    first = _start(home)
    _wait_for(lambda: held, [first], "the first run never recorded its request")
    second = _start(home)
    _wait_for(lambda: _waits_for_the_lock(second, home), [first, second], "the second run never waited")
    proxy.release.set()
    (rc1, out1, err1), (rc2, out2, err2) = _finish(first), _finish(second)
    assert rc1 == 0 and rc2 == 0, (err1, err2)
    assert "1 model(s) allocated" in out1 and not out1.startswith("already paid")
    assert out2.startswith("already paid") and "nothing was paid again" in out2
    rid1 = out1.split("(request ")[1].split(")")[0]
    assert f"request {rid1} was allocated" in out2  # the same request, not a new one
    proxy.delay = 0.0
    assert ledger() == (1, PRICE)


@pytest.mark.timing
@pytest.mark.anvil
def test_two_identical_requests_started_together_pay_once(slow_home):
    """Two processes started at the same moment on one home: one pays, the
    other waits for it (the pending file's lock) and reports that allocation."""
    home, proxy, ledger = slow_home
    proxy.delay = 0.1
    proxy.hold = _paid_request
    runs = [_start(home), _start(home)]
    # One holds the lock, the other waits for it, before either can have paid.
    _wait_for(lambda: all(_waits_for_the_lock(p, home) for p in runs), runs, "the two runs never overlapped")
    proxy.release.set()
    results = [_finish(p) for p in runs]
    assert [rc for rc, _, _ in results] == [0, 0], [err for _, _, err in results]
    outs = sorted((out for _, out, _ in results), key=lambda o: o.startswith("already paid"))
    assert not outs[0].startswith("already paid") and outs[1].startswith("already paid"), outs
    proxy.delay = 0.0
    assert ledger() == (1, PRICE)
    # A request made after both finished is a new request and pays again, as before.
    assert _finish(_start(home))[0] == 0
    assert ledger() == (2, 2 * PRICE)
