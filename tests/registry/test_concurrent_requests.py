"""Payments stay single when runs overlap (issue 20, items 7 and 8), against anvil.

A loopback proxy in front of anvil delays every JSON-RPC call (a slow node,
``registry_helpers.RpcProxy``), and ``medc-registry request`` runs as separate processes sharing
one home: a second run started while the first still waits on the slow node, and two runs
started together. Each must end with one allocation and one payment; the later run reports the
earlier run's allocation.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from medc_registry.nodes import start_anvil
from registry_helpers import PRICE, REQUEST, RpcProxy, cli_home, ledger


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
    return subprocess.Popen([sys.executable, "-m", "medc_registry.cli", *home, *REQUEST],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))


def _finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=240)
    return proc.returncode, out, err


@pytest.mark.anvil
@pytest.mark.slow
def test_a_second_run_during_a_slow_first_run_pays_nothing_more(slow_home):
    """Issue 20, item 7: with a node answering in 0.4 s per call, a second run of the same request
    started 2 s after the first (which is still ranking) resolves the first run's request."""
    home, proxy, ledger = slow_home
    proxy.delay = 0.4
    first = _start(home)
    time.sleep(2.0)
    assert first.poll() is None  # still at work on the slow node
    second = _start(home)
    (rc1, out1, err1), (rc2, out2, err2) = _finish(first), _finish(second)
    assert rc1 == 0 and rc2 == 0, (err1, err2)
    assert "1 model(s) allocated" in out1 and not out1.startswith("already paid")
    assert out2.startswith("already paid") and "nothing was paid again" in out2
    rid1 = out1.split("(request ")[1].split(")")[0]
    assert f"request {rid1} was allocated" in out2  # the same request, not a new one
    proxy.delay = 0.0
    assert ledger() == (1, PRICE)


@pytest.mark.anvil
def test_two_identical_requests_started_together_pay_once(slow_home):
    """Issue 20, item 8: two processes started at the same moment on one home: one pays, the
    other waits for it (the pending file's lock) and reports that allocation."""
    home, proxy, ledger = slow_home
    proxy.delay = 0.1
    runs = [_start(home), _start(home)]
    results = [_finish(p) for p in runs]
    assert [rc for rc, _, _ in results] == [0, 0], [err for _, _, err in results]
    outs = sorted((out for _, out, _ in results), key=lambda o: o.startswith("already paid"))
    assert not outs[0].startswith("already paid") and outs[1].startswith("already paid"), outs
    proxy.delay = 0.0
    assert ledger() == (1, PRICE)
    # A request made after both finished is a new request and pays again, as before.
    assert _finish(_start(home))[0] == 0
    assert ledger() == (2, 2 * PRICE)
