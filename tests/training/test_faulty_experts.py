"""Each faulty expert behaves as the paper describes; incompatible experts are rejected."""

import pytest
import torch
from medc_training.experts import (
    BiasedExpert,
    Expert,
    ExpertError,
    MaliciousExpert,
    RandomExpert,
    parse_expert,
)
from medc_training.qos import QOS_EXACT, attribute_distance, expert_weights_from_attributes, qos


class FixedExpert(Expert):
    """Always ranks moves by a fixed vector (a stand-in for a trained model's preference)."""

    def __init__(self, scores):
        self.fixed = torch.tensor(scores, dtype=torch.float32)

    def scores(self, obs, mask):
        return self.fixed.expand(mask.shape[0], -1).masked_fill(~mask, float("-inf"))


OBS = torch.zeros(3, 5, 4, 4)
ALL = torch.ones(3, 8, dtype=torch.bool)


def test_biased_expert_always_suggests_its_action_only():
    scores = BiasedExpert(6).scores(OBS, ALL)
    assert (scores.argmax(-1) == 6).all()
    assert torch.isinf(scores[:, [0, 1, 2, 3, 4, 5, 7]]).all()


def test_biased_expert_blocked_action_suggests_nothing():
    mask = ALL.clone()
    mask[:, 6] = False
    assert torch.isinf(BiasedExpert(6).scores(OBS, mask)).all()


def test_random_expert_ranks_valid_moves_uniformly_at_random():
    gen = torch.Generator().manual_seed(3)
    expert = RandomExpert(gen)
    mask = torch.ones(4000, 8, dtype=torch.bool)
    mask[:, 0] = False
    best = expert.scores(torch.zeros(4000, 1, 1, 1), mask).argmax(-1)
    counts = torch.bincount(best, minlength=8).float() / 4000
    assert counts[0].item() == 0.0
    assert counts[1:].tolist() == pytest.approx([1 / 7] * 7, abs=0.03)


@pytest.mark.parametrize("best,opposite", [(0, 4), (1, 5), (2, 6), (3, 7), (4, 0), (7, 3)])
def test_malicious_expert_suggests_the_opposite_direction(best, opposite):
    ranking = [0.0] * 8
    ranking[best] = 5.0
    malicious = MaliciousExpert(FixedExpert(ranking))
    malicious.check_compatible((5, 4, 4), 8)
    assert malicious.scores(OBS, ALL).argmax(-1).tolist() == [opposite] * 3


def test_malicious_opposite_survives_a_wall_on_the_inner_best():
    ranking = [5.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # inner says N
    mask = ALL.clone()
    mask[:, 0] = False                                   # N is blocked here, S (4) is free
    malicious = MaliciousExpert(FixedExpert(ranking))
    assert malicious.scores(OBS, mask).argmax(-1).tolist() == [4] * 3


def test_unknown_expert_spec_and_bad_biased_action_are_rejected():
    with pytest.raises(ExpertError, match="neither a bundle file"):
        parse_expert("no/such/file.safetensors")
    with pytest.raises(ExpertError, match="action index"):
        parse_expert("biased:left")
    with pytest.raises(ExpertError, match="not one of the 8 actions"):
        parse_expert("biased:9").check_compatible((5, 4, 4), 8)


def test_malicious_needs_an_opposite_table_for_unusual_action_sets():
    with pytest.raises(ExpertError, match="opposite"):
        MaliciousExpert(BiasedExpert(0)).check_compatible((5, 4, 4), 5)


def test_qos_exact_match_does_not_divide_by_zero():
    attrs = {"agents": 3, "walls": 2}
    assert attribute_distance(attrs, attrs) == 0
    assert qos(attribute_distance(attrs, attrs)) == QOS_EXACT  # the contract's D_m = 0 rule, no floor
    assert qos(attribute_distance(attrs, attrs)) > qos(attribute_distance({"agents": 1, "walls": 2}, attrs))
    # The exact match takes the whole roulette wheel; the other expert is never drawn.
    assert expert_weights_from_attributes([{"agents": 1, "walls": 2}, attrs], attrs) == [0.0, 1.0]
