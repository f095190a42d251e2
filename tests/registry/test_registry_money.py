"""Money that cannot be griefed: a request quotes, then pays only under a price limit per model
(given, or 10 x the cheapest non-zero price the request could get), equal QoS goes to the cheaper
model (then the lower id), and a total over the caller's allowance is refused before anything is
signed. Each hostile price list is built here on the embedded chain; every test reads what was
paid and owed straight from the contract."""

from __future__ import annotations

import pytest
from medc_registry.chain import ContractRevert
from medc_registry.journal import OverBudget, PendingRequests
from medc_registry.ranker import DEFAULT_PRICE_FACTOR
from registry_helpers import APP, PRICE

ETH = 10**18
A3W2 = {"agents": 3, "walls": 2}


def test_a_1000_eth_exact_match_beside_cheap_ones_is_never_paid(registry, users):
    """The measured grief: exact matches at 1,000 ETH (the lowest id), 0.001 ETH and free. A request
    without a limit gets the free one (equal QoS: the cheaper); with the free one gone, the
    0.001 ETH one; the 1,000 ETH owner is never paid."""
    griefer, honest, free_owner, requester = users
    dear = griefer.share_model(b"dear", APP, A3W2, 1000 * ETH)
    cheap = honest.share_model(b"cheap", APP, A3W2, PRICE)
    free = free_owner.share_model(b"free", APP, A3W2, 0)
    assert dear.model_id < cheap.model_id < free.model_id
    allocs = requester.request_models(APP, A3W2)
    assert [a.model_id for a in allocs] == [free.model_id] and allocs[0].price_wei == 0
    allocs = requester.request_models(APP, A3W2, count=2)  # the two cheapest exact matches
    assert sorted(a.model_id for a in allocs) == [cheap.model_id, free.model_id]
    assert sum(a.price_wei for a in allocs) == PRICE
    assert registry.owed(griefer.address) == 0 and registry.owed(honest.address) == PRICE
    # Asked for all three, it still passes the 1,000 ETH one over: it is over the default limit.
    allocs = requester.request_models(APP, A3W2, count=3)
    assert sorted(a.model_id for a in allocs) == [cheap.model_id, free.model_id]
    assert registry.owed(griefer.address) == 0


def test_a_lone_exact_match_priced_far_above_the_market_is_passed_over(registry, users):
    """No honest exact match: the griefer's exact match at 1,000 ETH would rank first, but the
    default limit is 10 x the cheapest non-zero price (0.001 ETH), so the near model is paid."""
    griefer, honest, _, requester = users
    griefer.share_model(b"dear", APP, A3W2, 1000 * ETH)
    near = honest.share_model(b"near", APP, {"agents": 3, "walls": 1}, PRICE)
    quotes: list = []
    allocs = requester.request_models(APP, A3W2, on_quote=quotes.append)
    assert [a.model_id for a in allocs] == [near.model_id] and allocs[0].price_wei == PRICE
    limit = quotes[0].limit
    assert (limit.wei, limit.given, limit.reference_wei) == (DEFAULT_PRICE_FACTOR * PRICE, False, PRICE)
    assert limit.passed_over == 1 and "1 dearer model(s) passed over" in limit.describe()
    assert registry.owed(griefer.address) == 0
    # Named explicitly, a limit that covers it is the caller's choice.
    ids, price = requester.quote(APP, A3W2, max_price=1000 * ETH)
    assert price == 1000 * ETH and ids != [near.model_id]


def test_equal_qos_goes_to_the_cheaper_model_then_the_lower_id(registry, users):
    """Exact matches of equal reputations tie: the contract alone would take the lowest ids
    (3P, P); the request takes the cheapest (P, P in id order), and for non-exact models of equal
    QoS the same."""
    a, b, c, requester = users
    first = a.share_model(b"first", APP, A3W2, 3 * PRICE)
    second = b.share_model(b"second", APP, A3W2, PRICE)
    third = c.share_model(b"third", APP, A3W2, PRICE)
    fourth = a.share_model(b"fourth", APP, A3W2, 2 * PRICE)
    assert requester.quote(APP, A3W2) == ([second.model_id], PRICE)
    ids, price = requester.quote(APP, A3W2, count=2)
    assert sorted(ids) == [second.model_id, third.model_id] and price == 2 * PRICE
    ids, price = requester.quote(APP, A3W2, count=3)
    assert sorted(ids) == [second.model_id, third.model_id, fourth.model_id] and price == 4 * PRICE
    before = registry.owed(a.address)
    allocs = requester.request_models(APP, A3W2, count=2)
    assert sorted(x.model_id for x in allocs) == [second.model_id, third.model_id]
    assert registry.owed(a.address) == before and registry.owed(b.address) == PRICE
    # Non-exact, equal QoS (one wall off either way): the cheaper one, though its id is higher.
    far_dear = a.share_model(b"up", APP, {"agents": 3, "walls": 5}, 2 * PRICE)
    up = b.share_model(b"up", APP, {"agents": 3, "walls": 3}, 2 * PRICE)
    down = c.share_model(b"down", APP, {"agents": 3, "walls": 1}, PRICE)
    assert far_dear.model_id < up.model_id < down.model_id
    ids, _ = requester.quote(APP, A3W2, count=5)
    assert set(ids) == {second.model_id, third.model_id, fourth.model_id, first.model_id, down.model_id}


def test_a_higher_reputation_still_ranks_before_a_lower_price(registry, users):
    """Price breaks ties only: an exact match with a better reputation product is taken at its
    price (within the limit) before a cheaper one with a worse one."""
    a, b, _, requester = users
    good = a.share_model(b"good", APP, A3W2, 5 * PRICE)
    plain = b.share_model(b"plain", APP, A3W2, PRICE)
    alloc = requester.request_models(APP, A3W2, count=2)
    by_id = {x.model_id: x for x in alloc}
    requester.review(by_id[good.model_id], 1.0)  # good's reputation goes up
    requester.review(by_id[plain.model_id], 0.0)  # plain's goes down
    assert requester.quote(APP, A3W2) == ([good.model_id], 5 * PRICE)


def test_free_models_only_when_everything_the_request_could_get_is_free(registry, users):
    a, b, _, requester = users
    free = a.share_model(b"free", APP, {"agents": 1, "walls": 1}, 0)
    quotes: list = []
    allocs = requester.request_models(APP, A3W2, on_quote=quotes.append)
    assert [x.model_id for x in allocs] == [free.model_id] and quotes[0].limit.wei == 0
    assert "free models only" in quotes[0].limit.describe()
    # The requester's own priced model is not one it could get: it sets no reference.
    requester.share_model(b"own", APP, A3W2, PRICE)
    allocs = requester.request_models(APP, A3W2, on_quote=quotes.append)
    assert [x.model_id for x in allocs] == [free.model_id] and quotes[-1].limit.wei == 0
    # Nor does a model under the request's minimum reputation.
    b.share_model(b"priced", APP, {"agents": 2, "walls": 2}, PRICE)
    with pytest.raises(ContractRevert, match="NoEligibleModels"):
        requester.quote(APP, A3W2, min_model_rep=0.9)
    allocs = requester.request_models(APP, A3W2, on_quote=quotes.append)
    assert quotes[-1].limit.reference_wei == PRICE  # now a priced model it could get exists


def test_a_quote_over_the_total_allowed_is_refused_before_anything_is_signed(registry, users, tmp_path):
    a, b, _, requester = users
    a.share_model(b"one", APP, A3W2, PRICE)
    b.share_model(b"two", APP, A3W2, PRICE)
    requester.pending = PendingRequests(tmp_path / "pending.json")
    count_before = registry.chain.call(registry.models.functions.allocationCount())
    balance = registry.chain.balance(requester.address)
    with pytest.raises(OverBudget, match="nothing was signed or sent"):
        requester.request_models(APP, A3W2, count=2, max_total=2 * PRICE - 1)
    with pytest.raises(OverBudget, match="payment"):
        requester.request_models(APP, A3W2, payment=3 * PRICE, max_total=2 * PRICE)
    assert registry.chain.call(registry.models.functions.allocationCount()) == count_before
    assert registry.chain.balance(requester.address) == balance  # no transaction, no gas
    assert requester.pending.load() == {}  # no record left behind
    allocs = requester.request_models(APP, A3W2, count=2, max_total=2 * PRICE)
    assert sum(x.price_wei for x in allocs) == 2 * PRICE
    with pytest.raises(ContractRevert, match="NoEligibleModels") as info:
        requester.request_models(APP, A3W2, max_price=PRICE - 1)
    assert "given" in info.value.values["limit"]


def test_equal_qos_goes_to_the_cheapest_across_ranking_pages(registry, users, monkeypatch):
    """Ten exact matches, the dearest shared first (10P ... P). With ranking pages of three
    candidates (the contract takes up to 256; a small page makes the paging run here), the two
    cheapest are taken, found page by page and round by round among the equally ranked rest."""
    from medc_registry import ranker

    monkeypatch.setattr(ranker, "MAX_CANDIDATES", 5)
    owners, requester = users[:3], users[3]
    models = [owners[i % 3].share_model(b"m%d" % i, APP, A3W2, (10 - i) * PRICE) for i in range(10)]
    near = owners[0].share_model(b"near", APP, {"agents": 3, "walls": 1}, 0)
    ids, price = requester.quote(APP, A3W2, count=2)
    assert sorted(ids) == [models[8].model_id, models[9].model_id] and price == 3 * PRICE
    ids, price = requester.quote(APP, A3W2, count=3)
    assert sorted(ids) == [m.model_id for m in models[7:]] and price == 6 * PRICE
    assert near.model_id not in ids  # free, but an exact match ranks first at any price in the limit
    allocs = requester.request_models(APP, A3W2, count=2)
    assert sorted(a.model_id for a in allocs) == [models[8].model_id, models[9].model_id]
    assert sum(a.price_wei for a in allocs) == 3 * PRICE
