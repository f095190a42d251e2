"""Payments: owners credited per allocation, refunds, pull withdrawals, reentrancy refused."""

from __future__ import annotations

import pytest
from medc_registry.chain import ContractRevert, decode_error_data
from registry_helpers import APP, PRICE, revert_of
from web3.logs import DISCARD


def _fee(chain, result):
    return result.gas_used * result.receipt["effectiveGasPrice"]


def test_owner_shares_and_refund_then_withdraw(registry, users):
    a, b, r = users[0], users[1], users[3]
    a.share_model(b"a", APP, {"agents": 3, "walls": 2}, PRICE)
    b.share_model(b"b", APP, {"agents": 3, "walls": 1}, 3 * PRICE)
    chain = registry.chain
    before = chain.balance(r.address)
    allocs = r.request_models(APP, {"agents": 3, "walls": 2}, count=5, payment=10 * PRICE)
    assert r.last_tx is not None and r.last_tx.receipt["status"] == 1 and r.last_tx.gas_used > 100_000
    assert len(allocs) == 2  # fewer available than requested: only those are charged
    assert a.owed() == PRICE and b.owed() == 3 * PRICE
    assert r.owed() == 6 * PRICE  # the overpayment is credited back
    assert chain.balance(registry.deployment.models) == 10 * PRICE
    # Nothing else left the requester's account but the payment and the fee.
    spent = before - chain.balance(r.address)
    assert spent > 10 * PRICE and spent - 10 * PRICE < 10**16

    for user, amount in ((a, PRICE), (b, 3 * PRICE), (r, 6 * PRICE)):
        bal = chain.balance(user.address)
        result = chain.transact(registry.models.functions.withdraw(), sender=user.address)
        assert chain.balance(user.address) == bal + amount - _fee(chain, result)
        assert user.owed() == 0
    assert chain.balance(registry.deployment.models) == 0


def test_exact_payment_by_default_and_quote(registry, users):
    users[0].share_model(b"a", APP, {"agents": 3, "walls": 2}, 2 * PRICE)
    users[1].share_model(b"free", APP, {"agents": 1, "walls": 2}, 0)
    ids, total = users[3].quote(APP, {"agents": 3, "walls": 2}, count=2)
    assert ids == [0, 1] and total == 2 * PRICE
    users[3].request_models(APP, {"agents": 3, "walls": 2}, count=2)
    assert users[3].owed() == 0 and users[0].owed() == 2 * PRICE and users[1].owed() == 0
    with pytest.raises(ValueError, match="payment"):
        users[3].request_models(APP, {"agents": 3, "walls": 2}, payment=-1)


def test_withdraw_with_nothing_owed_reverts(registry, users):
    with pytest.raises(ContractRevert) as exc:
        users[0].withdraw()
    assert revert_of(exc).error == "NothingToWithdraw"
    assert "nothing is owed" in str(exc.value)


def test_reentrant_withdraw_is_refused(registry, users):
    chain = registry.chain
    attacker = chain.contract(
        "ReentrantWithdrawer",
        chain.deploy(
            "ReentrantWithdrawer", registry.deployment.models, registry.deployment.users, sender=5
        ).contract_address,
    )
    chain.transact(attacker.functions.register(), sender=5)
    chain.transact(attacker.functions.share(APP, "QmAttackerModel", [3, 2], PRICE), sender=5)
    users[0].share_model(b"honest", APP, {"agents": 3, "walls": 2}, PRICE)
    users[3].request_models(APP, {"agents": 3, "walls": 2}, count=2)  # pays the attacker and the honest owner
    assert registry.owed(attacker.address) == PRICE
    escrow = chain.balance(registry.deployment.models)
    result = chain.transact(attacker.functions.attack(), sender=5)
    assert chain.call(attacker.functions.receiveCount()) == 1
    assert chain.call(attacker.functions.reentrySucceeded()) is False
    # The nested call hit NothingToWithdraw: the balance was zeroed before the transfer.
    err = bytes(chain.call(attacker.functions.reentryError()))
    assert decode_error_data(err).error == "NothingToWithdraw"
    assert chain.balance(attacker.address) == PRICE
    assert chain.balance(registry.deployment.models) == escrow - PRICE == registry.owed(users[0].address)
    withdrawn = registry.models.events.Withdrawn().process_receipt(result.receipt, errors=DISCARD)
    assert [e["args"]["amount"] for e in withdrawn] == [PRICE]
