"""``medc-registry request`` against anvil, as separate processes: it quotes and states its limit
before it pays, never pays a griefer's 1,000 ETH exact match, pays once for two runs started at
the same instant however the machine schedules them, and answers Ctrl-C while it waits for
another run's payment with one line (no traceback, nothing paid)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from child_signals import default_sigint
from medc_registry.home import PENDING_FILE
from medc_registry.nodes import start_anvil
from registry_helpers import APP, PRICE, REQUEST, cli_home, ledger

ETH = 10**18


@pytest.fixture
def home(tmp_path, capsys):
    """(home argv, ledger(), chain, models contract) of a CLI home on anvil: account 1 shares a
    model at 0.001 ETH (A1W3), account 2 requests."""
    from medc_registry import ChainClient

    anvil = start_anvil(tmp_path / "anvil")
    try:
        keys = anvil.extra["private_keys"][:4]
        argv, models = cli_home(tmp_path, keys, anvil.url, capsys)
        chain = ChainClient.connect(anvil.url, keys)
        yield argv, (lambda: ledger(anvil.url, keys, models)), chain, chain.contract("ModelsManager", models)
    finally:
        anvil.stop()


def _start(home: list[str], *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "medc_registry.cli", "--deadline", "120", *home, *REQUEST,
                             *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint)


def _finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out, err


@pytest.mark.anvil
def test_the_cli_quotes_states_its_limit_and_never_pays_the_griefers_price(home, capsys):
    """Account 3 shares the requesters' exact match at 1,000 ETH: the request says its limit
    (10 x 0.001 ETH) and what it passed over, and pays the 0.001 ETH model."""
    from medc_registry.cli import main as cli_main

    argv, books, chain, mmc = home
    assert cli_main([*argv, "register", "--account", "3"]) == 0
    chain.transact(mmc.functions.addModel(APP, "QmGrief", "", [3, 2], 1000 * ETH), sender=3)
    capsys.readouterr()
    assert cli_main([*argv, *REQUEST]) == 0
    out = capsys.readouterr().out
    quote = out.splitlines()[0]
    assert quote.startswith("quote: 1 model(s) for 0.001 ETH; limit at most 0.01 ETH per model"), out
    assert "1 dearer model(s) passed over (name a higher limit to consider them)" in quote
    assert books() == (1, PRICE)
    assert chain.call(mmc.functions.owed(chain.addresses[3])) == 0
    # A limit given explicitly is stated as given; a total under the quote pays nothing.
    assert cli_main([*argv, *REQUEST, "--max-total", "0.0009"]) == 2
    err = capsys.readouterr().err
    assert "over the 0.0009 ETH allowed in total; nothing was signed or sent" in err
    assert "Traceback" not in err
    assert books() == (1, PRICE)


@pytest.mark.timing
@pytest.mark.anvil
def test_two_runs_started_at_the_same_instant_pay_once_even_when_one_runs_to_the_end_first(home):
    """Both processes start at the same moment; the second is stopped at once (SIGSTOP: the
    scheduler of a loaded machine at its worst) until the first has paid and exited. The second
    then finds the first's payment, confirmed after its own start, and pays nothing."""
    argv, books, _chain, _mmc = home
    runs = [_start(argv), _start(argv)]
    os.kill(runs[1].pid, signal.SIGSTOP)
    try:
        rc1, out1, err1 = _finish(runs[0])
    finally:
        os.kill(runs[1].pid, signal.SIGCONT)
    rc2, out2, err2 = _finish(runs[1])
    assert (rc1, rc2) == (0, 0), (err1, err2)
    assert "1 model(s) allocated" in out1 and "already paid" not in out1
    assert "already paid" in out2 and "nothing was paid again" in out2, out2
    rid1 = out1.split("(request ")[1].split(")")[0]
    assert f"request {rid1} was allocated" in out2
    assert books() == (1, PRICE)
    # A run started after both ended is a new request and pays.
    assert _finish(_start(argv))[0] == 0
    assert books() == (2, 2 * PRICE)


def _has_open(proc: subprocess.Popen, path: Path) -> bool:
    fds = Path(f"/proc/{proc.pid}/fd")
    with contextlib.suppress(OSError):
        for fd in os.listdir(fds):
            with contextlib.suppress(OSError):
                if os.readlink(fds / fd) == str(path):
                    return True
    return False


@pytest.mark.timing
@pytest.mark.anvil
def test_ctrl_c_while_waiting_for_the_payment_lock_prints_one_line(home):
    """Another run holds the home's payment lock; Ctrl-C on the waiting run ends it with one
    clear line, status 130, and nothing paid."""
    argv, books, _chain, _mmc = home
    lock = Path(argv[1]) / f"{PENDING_FILE}.lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # the other run's request, in progress
        proc = _start(argv)
        deadline = time.monotonic() + 180
        while not _has_open(proc, lock):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the run never waited for the lock"
            time.sleep(0.05)
        time.sleep(0.3)  # inside the wait
        proc.send_signal(signal.SIGINT)
        rc, out, err = _finish(proc)
    finally:
        os.close(fd)
    assert rc == 130, (out, err)
    assert err.strip().count("\n") == 0 and "Traceback" not in err, err
    assert "interrupted while waiting for another run's request" in err and "paid nothing" in err
    assert books() == (0, 0)
