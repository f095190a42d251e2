"""The parts a ChainClient is made of, each on its own: its retry policy on a fake clock and its
transaction sender on a fake node, without a chain."""

from __future__ import annotations

import pytest
from medc_registry.chain import ChainError, RetryPolicy, TxSender


class _Time:
    """A clock that moves only when the policy sleeps (or the test says)."""

    def __init__(self) -> None:
        self.now = 0.0
        self.pauses: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.pauses.append(seconds)
        self.now += seconds


def _policy(t: _Time, **kw) -> RetryPolicy:
    options = {"retries": 3, "backoff": 0.25, "deadline": 60.0, **kw}
    return RetryPolicy(clock=t.clock, sleep=t.sleep, **options)


def test_a_transient_error_is_retried_with_a_doubling_backoff_and_others_are_raised_at_once():
    t = _Time()
    policy = _policy(t)
    answers = [ConnectionError("reset"), TimeoutError("slow"), 7]

    def op():
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    assert policy.call(op, "read a number") == 7 and t.pauses == [0.25, 0.5]
    with pytest.raises(ValueError, match="bad"):
        policy.call(lambda: (_ for _ in ()).throw(ValueError("bad")), "read")
    with pytest.raises(ChainError, match=r"could not read after 4 attempts: down"):
        policy.call(lambda: (_ for _ in ()).throw(ConnectionError("down")), "read")
    assert t.pauses[2:] == [0.25, 0.5, 1.0] and policy.time_left() is None


def test_one_deadline_covers_a_call_its_pauses_and_the_calls_nested_in_it():
    t = _Time()
    policy = _policy(t, retries=10, backoff=1.0, deadline=5.0)
    with policy.window():
        t.now += 1.0
        with policy.window():  # nested: the outer call's deadline
            assert policy.time_left() == 4.0
        with pytest.raises(ChainError, match=r"could not read within the 5 s deadline: down"):
            policy.call(lambda: (_ for _ in ()).throw(ConnectionError("down")), "read")
        assert t.pauses == [1.0, 2.0, 1.0]  # the last pause cut to what was left
    assert policy.time_left() is None
    with pytest.raises(ValueError, match="deadline must be a positive number"):
        RetryPolicy(deadline=0)


class _Eth:
    """A node that loses the first sending of a transaction, then mines it."""

    def __init__(self, status: int = 1) -> None:
        self.sent: list[bytes] = []
        self.mined: dict | None = None
        self.status = status

    def send_raw_transaction(self, raw: bytes) -> None:
        self.sent.append(raw)
        if len(self.sent) == 1:
            raise ConnectionError("connection reset")
        self.mined = {"status": self.status, "transactionHash": b"\x01" * 32, "gasUsed": 21_000,
                      "blockNumber": 5, "contractAddress": None}

    def get_transaction_receipt(self, tx_hash: str):
        from web3.exceptions import TransactionNotFound

        if self.mined is None:
            raise TransactionNotFound(tx_hash)
        return self.mined

    def wait_for_transaction_receipt(self, tx_hash: str, timeout: float, poll_latency: float):
        return self.get_transaction_receipt(tx_hash)


def test_the_sender_re_sends_the_same_bytes_after_a_lost_sending_and_returns_the_receipt():
    from types import SimpleNamespace

    t, eth = _Time(), _Eth()
    policy = _policy(t)
    sender = TxSender(SimpleNamespace(eth=eth), policy)
    with policy.window():
        result = sender.send(b"signed", None, None, 0)
    assert eth.sent == [b"signed", b"signed"] and t.pauses == [0.25]
    assert (result.tx_hash, result.gas_used, result.block_number) == ("0x" + "01" * 32, 21_000, 5)

    eth = _Eth(status=0)  # mined, but reverted: no contract call to say why
    with policy.window(), pytest.raises(ChainError, match="reverted"):
        TxSender(SimpleNamespace(eth=eth), policy).send(b"signed", None, None, 0)
