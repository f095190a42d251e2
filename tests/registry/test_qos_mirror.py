"""medc_training.qos against the deployed ModelsManager, bit for bit, on randomised cases.

200 (model, request) cases over 1 to 8 features: random values (including 0 and 2**32 - 1),
exact matches, all-zero environments, equal and random weights, and reputations moved by
random reviews between requests. Every allocation's D_m and QoS (the ModelAllocated event's
fixed-point integers) must equal the Python mirror's, and the allocation order must be the
mirror's ranking key (ties by the lower model id).
"""

from __future__ import annotations

import random

from medc_training.qos import ONE, distance, qos, rank_key
from web3.logs import DISCARD

UINT32 = 2**32 - 1
MODELS_PER_APP = 5  # 8 applications x 5 requests x 5 models = 200 cases
REQUESTS_PER_APP = 5


def _features(rng: random.Random, p: int) -> list[int]:
    kind = rng.random()
    if kind < 0.1:
        return [0] * p
    if kind < 0.25:
        return [rng.choice((0, UINT32, UINT32 - 1, 2**31)) for _ in range(p)]
    if kind < 0.6:
        return [rng.randint(0, 4) for _ in range(p)]  # small, the paper's agents / walls range
    return [rng.randint(0, UINT32) for _ in range(p)]


def _weights(rng: random.Random, p: int) -> list[int]:
    if rng.random() < 0.5:
        return []  # equal weights: the contract's mean
    cuts = sorted(rng.randint(0, ONE) for _ in range(p - 1))
    weights = [b - a for a, b in zip([0, *cuts], [*cuts, ONE])]
    assert sum(weights) == ONE and len(weights) == p
    return weights


def test_python_mirror_equals_the_contract(registry, users):
    rng = random.Random(20260613)
    chain, mmc, umc = registry.chain, registry.models.functions, registry.users.functions
    owners, requester = users[:3], users[3]
    cases = exact = weighted = 0
    for p in range(1, 9):
        app = f"qos-mirror-p{p}"
        envs, model_ids = [], []
        for k in range(MODELS_PER_APP):
            env = _features(rng, p)
            owner = owners[k % len(owners)]
            chain.transact(mmc.addModel(app, f"cid-{p}-{k}", "", env, 0), sender=owner.address)
            model_ids.append(chain.call(mmc.modelCount()) - 1)
            envs.append(env)
        for r in range(REQUESTS_PER_APP):
            req = list(rng.choice(envs)) if r % 2 == 0 else _features(rng, p)  # half exact matches
            weights = _weights(rng, p)
            reps = {}
            for mid in model_ids:
                owner, _, _, _, model_rep, _, _ = chain.call(mmc.getModel(mid))
                reps[mid] = (chain.call(umc.reputationOf(owner)), model_rep)
            rid = rng.randbytes(32)
            result = chain.transact(
                mmc.allocateModels(rid, app, req, weights, len(model_ids), 0, 0, list(range(len(model_ids)))),
                sender=requester.address,
            )
            events = registry.models.events.ModelAllocated().process_receipt(result.receipt, errors=DISCARD)
            assert len(events) == len(model_ids)
            for ev in events:
                a = ev["args"]
                env = envs[model_ids.index(a["modelId"])]
                d = distance(env, req, weights)
                assert a["distance"] == d, (env, req, weights)
                assert a["qos"] == qos(d, *reps[a["modelId"]]), (env, req, weights, reps[a["modelId"]])
                cases += 1
                exact += d == 0
                weighted += bool(weights)
            expected = sorted(model_ids, key=lambda m: (-rank_key(distance(envs[model_ids.index(m)], req,
                                                                           weights), *reps[m]), m))
            assert [ev["args"]["modelId"] for ev in events] == expected
            for ev in events:  # reviews move Rep_m and Rep_owner for the next request
                if rng.random() < 0.6:
                    review = rng.choice((0, ONE, rng.randint(0, ONE)))
                    chain.transact(mmc.updateModelRep(ev["args"]["allocationId"], review),
                                   sender=requester.address)
    assert cases == 200
    assert exact >= 20 and 50 <= weighted <= 150  # the cases cover what they claim to
