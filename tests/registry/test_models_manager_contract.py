"""Models Manager: sharing, greedy QoS allocation, reviews (Rep_m, Rep_i) and their reverts."""

from __future__ import annotations

import math

import pytest
from medc_registry.chain import ContractRevert
from registry_helpers import APP, PRICE, revert_of
from web3.logs import DISCARD

ONE = 10**18
RID = b"\x01" * 32  # a request id (idempotency key)


def _share(user, env, price=PRICE, app=APP, data=None):
    return user.share_model(data or f"model {env} {user.address}".encode(), app, env, price)


def _raises(error, fn, *args, **kwargs):
    with pytest.raises(ContractRevert) as exc:
        fn(*args, **kwargs)
    assert revert_of(exc).error == error, str(exc.value)
    return exc.value


# ----------------------------------------------------------------------------- addModel
def test_share_model_records_every_field(registry, users):
    m = users[0].share_model(b"weights", APP, {"walls": 3, "agents": 1}, PRICE, {"architecture": "lenet5"}, 1)
    assert m.model_id == 0 and m.owner == users[0].address and m.application == APP
    assert m.cid.startswith("bafkrei") and registry.fetch(m.cid) == b"weights"
    assert m.features == ("agents", "walls") and m.env == (1, 3)
    assert m.env_features == {"agents": 1, "walls": 3}
    assert (m.price_wei, m.reputation, m.alloc_count, m.total_review) == (PRICE, 0.5, 0, 0.0)
    assert '"architecture":"lenet5"' in m.description
    assert (
        registry.model_count() == 1 and registry.list_models(APP) == [m] and registry.list_models("x") == []
    )


def test_a_shared_bundle_says_which_observation_its_model_takes(registry, users):
    import json

    from medc_training.bundle import bundle_bytes
    from medc_training.envs.tl_observation import observation_shape, parse_observation
    from medc_training.nets import make_actor_critic

    spec = parse_observation("ego3+estimate")
    net = make_actor_critic("mlp", observation_shape(spec, 13), 8)
    data = bundle_bytes(net, {"application": APP, "observation": {"name": spec.name},
                              "environment": {"agents": 1, "walls": 0, "grid": 13}})
    m = users[0].share_model(data, APP, {"agents": 1, "walls": 0}, PRICE)
    assert json.loads(m.description) == {"features": ["agents", "walls"], "observation": "ego3+estimate",
                                         "architecture": "mlp"}


def test_add_model_reverts(registry, users):
    mmc = registry.models.functions
    chain = registry.chain
    _raises("UnregisteredUser", registry.share_model, b"x", APP, {"agents": 1}, PRICE)
    cases = [
        (mmc.addModel(APP, "", "", [1], 0), "InvalidCid"),
        (mmc.addModel(APP, "Q" * 129, "", [1], 0), "InvalidCid"),
        (mmc.addModel("", "Qm1", "", [1], 0), "EmptyApplication"),
        (mmc.addModel(APP, "Qm1", "", list(range(9)), 0), "TooManyFeatures"),
        (mmc.addModel(APP, "Qm1", "", [1], 2**128), "PriceTooLarge"),
    ]
    for fn, error in cases:
        _raises(error, chain.transact, fn, sender=1)
    _share(users[0], {"agents": 1, "walls": 0})
    _raises("FeatureCountMismatch", chain.transact, mmc.addModel(APP, "Qm1", "", [1, 2, 3], 0), sender=1)
    _raises("UnknownModel", registry.model, 5)
    # The facade checks before sending anything.
    with pytest.raises(ValueError, match="features"):
        _share(users[1], {"agents": 1, "obstacles": 0})
    with pytest.raises(ValueError, match="integers"):
        _share(users[1], {"agents": -1, "walls": 0})
    with pytest.raises(ValueError, match="price"):
        _share(users[1], {"agents": 1, "walls": 0}, price=-1)


# ----------------------------------------------------------------------------- allocation
def _reference_order(models, req, weights=None, owner_rep=None):
    """Python statement of the paper's ranking: exact matches by Rep_i*Rep_m, then QoS, then id."""

    def key(m):
        p = len(req)
        diffs = [abs(a - b) for a, b in zip(m.env, req)]
        d = sum(w * x for w, x in zip(weights, diffs)) if weights else sum(diffs) / p
        rep = (owner_rep or {}).get(m.owner, 0.5) * m.reputation
        return (0, -rep, m.model_id) if d == 0 else (1, -rep / d, m.model_id)

    return [m.model_id for m in sorted(models, key=key)]


def test_allocation_ranks_by_qos_and_exact_match_first(registry, users):
    owners, requester = users[:3], users[3]
    envs = [
        {"agents": 1, "walls": 0},
        {"agents": 1, "walls": 3},
        {"agents": 3, "walls": 3},
        {"agents": 3, "walls": 2},
    ]
    models = [_share(owners[i % 3], env) for i, env in enumerate(envs)]
    req = {"agents": 3, "walls": 2}
    allocs = requester.request_models(APP, req, count=4)
    assert [a.model_id for a in allocs] == _reference_order(models, [3, 2]) == [3, 2, 1, 0]
    assert math.isinf(allocs[0].qos) and allocs[0].distance == 0.0  # D_m = 0 ranks first, no division
    assert allocs[1].distance == pytest.approx(0.5) and allocs[1].qos == pytest.approx(0.25 / 0.5)
    assert allocs[3].distance == pytest.approx(2.0) and allocs[3].qos == pytest.approx(0.25 / 2.0)
    assert [a.allocation_id for a in allocs] == [0, 1, 2, 3]
    assert all(a.requester == requester.address and a.price_wei == PRICE for a in allocs)


def test_weights_change_the_ranking(registry, users):
    a = _share(users[0], {"agents": 1, "walls": 2})  # differs in agents by 2
    b = _share(users[1], {"agents": 3, "walls": 5})  # differs in walls by 3
    req = {"agents": 3, "walls": 2}
    ids_equal, _ = users[3].quote(APP, req, count=2)
    ids_agents, _ = users[3].quote(APP, req, {"agents": 0.9, "walls": 0.1}, count=2)
    assert ids_equal == [a.model_id, b.model_id]  # D = 1.0 vs 1.5
    assert ids_agents == [b.model_id, a.model_id]  # D = 1.8 vs 0.3
    assert ids_agents == _reference_order([a, b], [3, 2], [0.9, 0.1])
    allocs = users[3].request_models(APP, req, {"agents": 0.9, "walls": 0.1}, count=1)
    assert allocs[0].distance == pytest.approx(0.3) and allocs[0].qos == pytest.approx(0.25 / 0.3)


def test_reputation_minimums_filter_and_own_models_are_skipped(registry, users):
    good = _share(users[0], {"agents": 3, "walls": 2})
    bad = _share(users[1], {"agents": 3, "walls": 2})
    own = _share(users[3], {"agents": 3, "walls": 2})
    r = users[3]
    first = r.request_models(APP, {"agents": 3, "walls": 2}, count=2)
    assert {a.model_id for a in first} == {good.model_id, bad.model_id}  # never its own model
    r.review(first[[a.model_id for a in first].index(bad.model_id)].allocation_id, 0.1)
    r.review(first[[a.model_id for a in first].index(good.model_id)].allocation_id, 0.9)
    allocs = r.request_models(APP, {"agents": 3, "walls": 2}, count=3, min_model_rep=0.5)
    assert [a.model_id for a in allocs] == [good.model_id]
    allocs = r.request_models(APP, {"agents": 3, "walls": 2}, count=3, min_owner_rep=0.5)
    assert [a.model_id for a in allocs] == [good.model_id]
    # All exact matches: ranked by Rep_i * Rep_m = 0.81 (good), 0.25 (unreviewed), 0.01 (bad).
    ranked = users[2].request_models(APP, {"agents": 3, "walls": 2}, count=3)
    assert [a.model_id for a in ranked] == [good.model_id, own.model_id, bad.model_id]
    _raises("NoEligibleModels", r.request_models, APP, {"agents": 3, "walls": 2}, min_model_rep=0.95)


def test_allocate_reverts(registry, users):
    _share(users[0], {"agents": 1, "walls": 0})
    r = users[3]
    mmc = registry.models.functions
    _raises("UnregisteredUser", registry.request_models, APP, {"agents": 1, "walls": 0}, payment=PRICE)
    _raises("UnknownApplication", r.request_models, "maze_cleaning", {"agents": 1}, payment=PRICE)
    cases = [
        (mmc.allocateModels(RID, "maze_cleaning", [1], [], 1, 0, 0, [0]), "UnknownApplication"),
        (mmc.allocateModels(RID, APP, [1, 0], [], 0, 0, 0, [0]), "InvalidCount"),
        (mmc.allocateModels(RID, APP, [1], [], 1, 0, 0, [0]), "FeatureCountMismatch"),
        (mmc.allocateModels(RID, APP, [1, 0], [ONE], 1, 0, 0, [0]), "InvalidWeights"),
        (mmc.allocateModels(RID, APP, [1, 0], [ONE // 2, ONE // 3], 1, 0, 0, [0]), "InvalidWeights"),
        (mmc.allocateModels(RID, APP, [1, 0], [], 1, ONE, 0, [0]), "NoEligibleModels"),
    ]
    for fn, error in cases:
        _raises(error, registry.chain.transact, fn, sender=r.address, value=PRICE)
    err = _raises("InsufficientPayment", r.request_models, APP, {"agents": 1, "walls": 0}, payment=PRICE - 1)
    assert err.values == {"required": PRICE, "sent": PRICE - 1}
    with pytest.raises(ValueError, match="count"):
        r.request_models(APP, {"agents": 1, "walls": 0}, count=0)
    with pytest.raises(ValueError, match="sum to 1"):
        r.request_models(APP, {"agents": 1, "walls": 0}, {"agents": 0.5, "walls": 0.6})


# ----------------------------------------------------------------------------- reviews
def test_reviews_update_model_and_owner_reputation(registry, users):
    owner, r1, r2 = users[0], users[2], users[3]
    m1 = _share(owner, {"agents": 3, "walls": 2})
    m2 = _share(owner, {"agents": 1, "walls": 0})
    a1 = r1.request_models(APP, {"agents": 3, "walls": 2}, count=2)
    a2 = r2.request_models(APP, {"agents": 3, "walls": 2}, count=1)
    assert owner.user().alloc_count == 3 and registry.model(m1.model_id).alloc_count == 2
    r1.review(a1[0].allocation_id, 1.0)  # m1
    assert registry.model(m1.model_id).reputation == pytest.approx(0.5)  # 1.0 / 2 allocations
    assert owner.user().reputation == pytest.approx(1 / 3)  # 1.0 / 3 allocations
    r2.review(a2[0].allocation_id, 0.6)  # m1 again
    r1.review(a1[1].allocation_id, 0.0)  # m2
    m1_after, m2_after = registry.model(m1.model_id), registry.model(m2.model_id)
    assert m1_after.reputation == pytest.approx(0.8) and m1_after.total_review == pytest.approx(1.6)
    assert m2_after.reputation == 0.0
    assert owner.user().reputation == pytest.approx(1.6 / 3) and owner.user().total_review == pytest.approx(
        1.6
    )
    assert registry.allocation(a1[0].allocation_id) == (r1.address, m1.model_id, True)


def test_review_reverts(registry, users):
    _share(users[0], {"agents": 3, "walls": 2})
    r = users[3]
    alloc = r.request_models(APP, {"agents": 3, "walls": 2})[0]
    _raises("UnknownAllocation", r.review, 99, 0.5)
    _raises("NotAllocatedRequester", users[1].review, alloc.allocation_id, 0.5)
    _raises(
        "NotAllocatedRequester", users[0].review, alloc.allocation_id, 1.0
    )  # the owner cannot self-review
    mmc = registry.models.functions
    _raises(
        "ReviewOutOfRange",
        registry.chain.transact,
        mmc.updateModelRep(alloc.allocation_id, ONE + 1),
        sender=r.address,
    )
    with pytest.raises(ValueError, match="between 0 and 1"):
        r.review(alloc.allocation_id, 1.5)
    with pytest.raises(ValueError, match="allocation id"):
        r.review("0", 0.5)
    r.review(alloc, 0.7)  # the Allocation itself works too
    _raises("AlreadyReviewed", r.review, alloc.allocation_id, 0.7)
    _raises("UnknownAllocation", registry.allocation, 99)


def test_events_on_every_state_change(registry, users):
    m = _share(users[0], {"agents": 3, "walls": 2})
    chain, mmc = registry.chain, registry.models
    tx = chain.transact(
        mmc.functions.allocateModels(RID, APP, [3, 2], [], 1, 0, 0, [0]),
        sender=users[3].address,
        value=2 * PRICE,
    )
    names = [
        e.event
        for e in (
            *mmc.events.ModelAllocated().process_receipt(tx.receipt, errors=DISCARD),
            *mmc.events.PaymentCredited().process_receipt(tx.receipt, errors=DISCARD),
        )
    ]
    assert names == ["ModelAllocated", "PaymentCredited", "PaymentCredited"]  # owner share + refund
    info = registry.users.events.UserInfoUpdated().process_receipt(tx.receipt, errors=DISCARD)[0]["args"]
    assert info["user"] == users[0].address and info["allocCount"] == 1
    rv = chain.transact(mmc.functions.updateModelRep(0, ONE), sender=users[3].address)
    assert (
        mmc.events.ModelReviewed().process_receipt(rv.receipt, errors=DISCARD)[0]["args"]["modelId"]
        == m.model_id
    )
    assert (
        registry.users.events.UserReputationUpdated().process_receipt(rv.receipt, errors=DISCARD)[0]["args"][
            "reputation"
        ]
        == ONE
    )


# ----------------------------------------------------------------------------- idempotent requests
def test_a_request_id_is_paid_and_allocated_at_most_once(registry, users):
    owner, r = users[0], users[3]
    _share(owner, {"agents": 3, "walls": 2})
    chain, mmc = registry.chain, registry.models.functions
    fn = mmc.allocateModels(RID, APP, [3, 2], [], 1, 0, 0, [0])
    chain.transact(fn, sender=r.address, value=PRICE)
    balance = chain.balance(r.address)
    err = _raises("RequestAlreadyPaid", chain.transact, fn, sender=r.address, value=PRICE)
    assert err.values == {"firstAllocationId": 0} and "nothing was paid again" in str(err)
    # The id is checked first: any other arguments with it are refused the same way.
    _raises(
        "RequestAlreadyPaid",
        chain.transact,
        mmc.allocateModels(RID, "", [], [], 0, 0, 0, []),
        sender=r.address,
    )
    assert chain.call(mmc.allocationCount()) == 1 and registry.owed(owner.address) == PRICE
    assert chain.balance(r.address) == balance  # the refused replays paid nothing (no gas: checked first)
    # Ids are per requester: another requester's same id is a new request.
    chain.transact(fn, sender=users[2].address, value=PRICE)
    assert chain.call(mmc.allocationCount()) == 2


def test_the_facade_replays_a_paid_request_id_instead_of_paying_again(registry, users):
    _share(users[0], {"agents": 3, "walls": 2})
    r = users[3]
    first = r.request_models(APP, {"agents": 3, "walls": 2}, request_id="order-42")
    again = r.request_models(APP, {"agents": 3, "walls": 2}, request_id="order-42")
    assert [a.allocation_id for a in again] == [a.allocation_id for a in first] == [0]
    assert not first[0].replayed and again[0].replayed and again[0].qos == first[0].qos
    assert registry.chain.call(registry.models.functions.allocationCount()) == 1
    assert registry.owed(users[0].address) == PRICE and r.pending_requests() == []


# ----------------------------------------------------------------------------- bounded allocation
def test_candidates_are_checked_and_bounded(registry, users):
    for env in ({"agents": 3, "walls": 2}, {"agents": 1, "walls": 0}):
        _share(users[0], env)
    _share(users[1], {"agents": 2, "walls": 2}, app="maze_cleaning")
    r, mmc = users[3], registry.models.functions

    def alloc(candidates):
        return mmc.allocateModels(RID, APP, [3, 2], [], 1, 0, 0, candidates)

    for candidates, error in (
        ([], "TooManyCandidates"),
        (list(range(257)), "TooManyCandidates"),
        ([1, 0], "InvalidCandidate"),  # not increasing
        ([0, 0], "InvalidCandidate"),  # twice
        ([0, 2], "InvalidCandidate"),  # another application's model
        ([0, 9], "InvalidCandidate"),  # no such model
    ):
        _raises(error, registry.chain.transact, alloc(candidates), sender=r.address, value=PRICE)
    # Ranked among the given candidates only (the facade passes the overall best).
    assert registry.chain.call(alloc([1]), sender=r.address, value=PRICE)[0] == [1]
    assert r.rank(APP, {"agents": 3, "walls": 2}, count=2) == [0, 1]


@pytest.mark.slow
def test_allocation_gas_does_not_grow_with_spam_models(registry, users):
    """More models than one call may rank: the facade ranks them in pages, and pays for the best."""
    spammer, honest, r = users[0], users[1], users[3]
    chain, mmc = registry.chain, registry.models.functions
    best = _share(honest, {"agents": 3, "walls": 2})
    for i in range(300):  # far from the requirements, so each loses to the honest model
        chain.transact(mmc.addModel(APP, f"Qm{i}", "", [100 + i, 100], 0), sender=spammer.address)
    _raises(
        "TooManyCandidates",
        chain.transact,
        mmc.allocateModels(RID, APP, [3, 2], [], 1, 0, 0, list(range(301))),
        sender=r.address,
        value=PRICE,
    )
    allocs = r.request_models(APP, {"agents": 3, "walls": 2})
    assert [a.model_id for a in allocs] == [best.model_id] and allocs[0].qos == math.inf
    assert r.last_tx.gas_used < 200_000  # the same as with one shared model: one candidate ranked
