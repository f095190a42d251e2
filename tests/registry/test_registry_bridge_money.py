"""The registry bridge's money, without ROS: any node of the graph may call request_experts, so a
call pays only under its price limit per expert (or the registry's default) and within what is left
of the bridge's budget; a quote over it, or a malformed limit, is refused before anything is
signed. The hostile price lists are built here on the embedded chain; what was paid and owed is
read from the contract."""

from __future__ import annotations

import json

import pytest
from medc_registry.bridge_node import DEFAULT_BUDGET, BridgeError, RegistryBridge, parse_budget
from medc_registry.chain import ChainError
from registry_helpers import APP, PRICE

ETH = 10**18
A3W2 = json.dumps({"agents": 3, "walls": 2})


def _allocations(registry) -> int:
    return registry.chain.call(registry.models.functions.allocationCount())


def test_the_default_budget_is_stated_and_small():
    assert parse_budget(DEFAULT_BUDGET) == ETH // 100
    assert parse_budget("1000wei") == 1000
    with pytest.raises(BridgeError, match="not an amount"):
        parse_budget("lots")


def test_one_call_cannot_make_the_bridge_pay_1000_eth(registry, users, tmp_path):
    """The measured grief: exact matches at 1,000 ETH (the lowest id), 0.001 ETH and free. Without
    a limit the call gets the free one; naming a limit that covers the 1,000 ETH model, the quote
    is over the bridge's budget and refused: nothing allocated, nothing owed to the griefer."""
    griefer, honest, free_owner, requester = users
    dear = griefer.share_model(b"dear", APP, {"agents": 3, "walls": 2}, 1000 * ETH)
    honest.share_model(b"cheap", APP, {"agents": 3, "walls": 2}, PRICE)
    free = free_owner.share_model(b"free", APP, {"agents": 3, "walls": 2}, 0)
    bridge = RegistryBridge(requester, tmp_path / "cache")
    allocs = bridge.request(APP, A3W2)
    assert [a.model_id for a in allocs] == [free.model_id] and bridge.spent_wei == 0
    made = _allocations(registry)
    with pytest.raises(BridgeError, match=r"over this bridge's budget: 0\.01 ETH left of 0\.01 ETH"):
        bridge.request(APP, A3W2, count=3, max_price_wei=str(1000 * ETH))
    assert _allocations(registry) == made and registry.owed(griefer.address) == 0
    assert bridge.spent_wei == 0
    assert dear.model_id < free.model_id


def test_the_budget_spans_calls(registry, users, tmp_path):
    owner, _, _, requester = users
    owner.share_model(b"one", APP, {"agents": 3, "walls": 2}, PRICE)
    bridge = RegistryBridge(requester, tmp_path / "cache", budget_wei=PRICE + PRICE // 2)
    assert sum(a.price_wei for a in bridge.request(APP, A3W2)) == PRICE
    assert bridge.spent_wei == PRICE
    made = _allocations(registry)
    with pytest.raises(BridgeError, match="over this bridge's budget"):
        bridge.request(APP, A3W2)
    assert _allocations(registry) == made and bridge.spent_wei == PRICE
    assert registry.owed(owner.address) == PRICE


@pytest.mark.parametrize("text", ["-1", "1e18", "0x10", "1" * 41, "\uff11\uff12", "1.5", str(2**128)])
def test_a_malformed_price_limit_is_refused_before_anything_is_sent(text, registry, users, tmp_path):
    owner, _, _, requester = users
    owner.share_model(b"one", APP, {"agents": 3, "walls": 2}, PRICE)
    bridge = RegistryBridge(requester, tmp_path / "cache")
    made = _allocations(registry)
    with pytest.raises(BridgeError, match="max_price_wei must be a whole number of wei"):
        bridge.request(APP, A3W2, max_price_wei=text)
    assert _allocations(registry) == made and bridge.spent_wei == 0


def test_a_payment_whose_outcome_is_unknown_counts_against_the_budget(tmp_path):
    """The node's answer is lost after the quote: the payment may have gone out, so the bridge
    counts it as spent (it may refuse sooner, never pay more than its budget)."""

    class LostAnswer:
        def request_models(self, *args, on_quote, **kwargs):
            on_quote(type("Quote", (), {"price_wei": 7 * PRICE})())
            raise ChainError("no answer from the node")

    bridge = RegistryBridge(LostAnswer(), tmp_path / "cache", budget_wei=10 * PRICE)
    with pytest.raises(BridgeError, match="no answer"):
        bridge.request(APP, A3W2)
    assert bridge.spent_wei == 7 * PRICE
    with pytest.raises(BridgeError, match="no answer"):
        bridge.request(APP, A3W2)
    assert bridge.spent_wei == 14 * PRICE  # over the budget: what is left is 0, never negative


def test_nothing_left_of_the_budget_still_gets_free_experts(registry, users, tmp_path):
    owner, _, _, requester = users
    free = owner.share_model(b"free", APP, {"agents": 3, "walls": 2}, 0)
    bridge = RegistryBridge(requester, tmp_path / "cache", budget_wei=0)
    assert [a.model_id for a in bridge.request(APP, A3W2, max_price_wei=str(ETH))] == [free.model_id]
    bridge.spent_wei = 5  # more than the budget (an unknown outcome counted)
    assert [a.model_id for a in bridge.request(APP, A3W2)] == [free.model_id]
