"""The one QoS module: the contract's D_m and QoS in fixed point, R_S, and the trainer's weights.

Bit-for-bit agreement with the deployed ModelsManager is checked in
tests/registry/test_qos_mirror.py; these are the rules themselves.
"""

import math

import pytest
import torch
from medc_training.cli.train import build_parser, config_from_args
from medc_training.config import TrainConfig
from medc_training.experts import BiasedExpert, RandomExpert
from medc_training.jobs import make_learner
from medc_training.ppo import Trainer
from medc_training.qos import (
    INITIAL_REPUTATION,
    ONE,
    QOS_EXACT,
    attribute_distance,
    distance,
    expert_weights_from_attributes,
    fixed_weights,
    normalised_weights,
    qos,
    rank_key,
    rep_product,
    selection_weights,
)

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=2, horizon=8,
            eval_envs=2, eval_steps=8, eval_episodes=2, total_steps=16, method="medc")


def test_distance_is_the_mean_with_one_rounding_down():
    assert distance([1, 0], [3, 2]) == 2 * ONE  # (2 + 2) / 2: w_i = 1/p, not 1 each
    assert distance([0, 0, 0], [1, 0, 0]) == ONE // 3 == 333_333_333_333_333_333  # floor once
    assert distance([0, 0, 0], [2, 0, 0]) == 2 * ONE // 3 == 666_666_666_666_666_666
    assert distance([], []) == 0  # no features: the contract's p = 0 rule
    assert distance([2**32 - 1], [0]) == (2**32 - 1) * ONE  # no overflow in Python either
    with pytest.raises(ValueError, match="features"):
        distance([1, 2], [1])


def test_weighted_distance_is_exact_and_the_weights_must_sum_to_one():
    w = fixed_weights([0.7, 0.3])
    assert w == [7 * ONE // 10, 3 * ONE // 10] and sum(w) == ONE
    assert distance([1, 0], [0, 1], w) == ONE  # 0.7 * 1 + 0.3 * 1
    assert distance([1, 0], [1, 1], w) == 3 * ONE // 10
    third = fixed_weights([1 / 3, 1 / 3, 1 / 3])
    assert sum(third) == ONE and third[-1] == ONE - 2 * third[0]  # the last weight absorbs rounding
    for bad in ([ONE], [ONE // 2, ONE // 3], [ONE + 1, -1]):
        with pytest.raises(ValueError, match="summing"):
            distance([1, 0], [0, 0], bad)
    for bad in ([0.5, 0.4], [1.0, float("nan")], [-0.5, 1.5], []):
        with pytest.raises(ValueError, match="weights"):
            fixed_weights(bad)


def test_non_integer_features_follow_the_same_rule_exactly():
    assert distance([0.5], [1.0]) == ONE // 2
    assert distance([2, 0.5], [3, 1.0]) == 3 * ONE // 4  # (1 + 0.5) / 2
    for bad in (True, float("inf"), "3"):
        with pytest.raises(ValueError, match="finite number"):
            distance([bad], [1])


def test_qos_has_no_floor_and_exact_matches_are_unbounded():
    assert rep_product() == ONE // 4
    assert qos(ONE) == ONE // 4  # 0.5 * 0.5 / 1
    assert qos(ONE // 2) == ONE // 2
    assert qos(ONE // 10) == 25 * ONE // 10  # D_m = 0.1: 2.5, not capped by a minimum distance
    assert qos(0) == QOS_EXACT
    assert qos(3 * ONE, ONE, ONE) == ONE // 3
    assert qos(ONE, 0, INITIAL_REPUTATION) == 0


def test_rank_key_orders_exact_matches_first_then_by_reputation():
    near = rank_key(1, ONE, ONE)  # the largest finite QoS there is
    exact_low, exact_high = rank_key(0, ONE // 10, ONE // 10), rank_key(0, ONE, ONE)
    assert exact_high > exact_low > near > rank_key(ONE) > rank_key(2 * ONE)
    assert rank_key(0, 0, 0) > near  # even with reputation 0


def test_selection_weights_are_qos_over_its_sum():
    assert selection_weights([ONE // 4, ONE // 2, ONE // 4]) == [0.25, 0.5, 0.25]
    assert selection_weights([0.25, 0.125]) == pytest.approx([2 / 3, 1 / 3])
    assert selection_weights([0, ONE]) == [0.0, 1.0]
    assert sum(selection_weights([1, 2, 3, 4, 5, 6, 7])) == pytest.approx(1.0)


def test_exact_matches_take_the_whole_wheel_shared_by_reputation():
    # From the registry client (floats, math.inf) and from the contract's integers alike.
    assert selection_weights([0.25, math.inf, 0.5, math.inf]) == [0.0, 0.5, 0.0, 0.5]
    assert selection_weights([ONE, QOS_EXACT]) == [0.0, 1.0]
    assert selection_weights([math.inf, math.inf, 9.0], [0.25, 0.75, 0.5]) == [0.25, 0.75, 0.0]
    with pytest.raises(ValueError, match="one rep product per QoS"):
        selection_weights([math.inf, 1.0], [0.25])


def test_selection_weights_refuse_what_is_not_a_wheel():
    for bad, match in (([], "at least one"), ([0, 0], "QoS 0"), ([-1.0, 2.0], ">= 0"),
                       ([float("nan"), 1.0], ">= 0")):
        with pytest.raises(ValueError, match=match):
            selection_weights(bad)
    with pytest.raises(ValueError, match="QoS 0"):  # exact matches whose reputations are all 0
        selection_weights([math.inf, 1.0], [0.0, 0.5])


def test_attribute_experts_without_a_common_attribute_count_as_the_nearest_inexact_match():
    target = {"agents": 3, "walls": 2, "grid": 13, "max_steps": 50}
    assert attribute_distance({"agents": 2, "walls": 2, "grid": 13, "max_steps": 50}, target) == ONE // 4
    assert attribute_distance(None, target) == ONE // 4  # one unit off in one of the 4 attributes
    assert attribute_distance({"colour": "red", "agents": True}, target) == ONE // 4  # not numeric
    assert attribute_distance({"agents": 1, "name": "x"}, target) == 2 * ONE  # only 'agents' shared
    w = expert_weights_from_attributes([None, {"agents": 1, "walls": 0, "grid": 13, "max_steps": 50}],
                                       target)
    assert w == [0.8, 0.2]  # D_m 0.25 and 1: QoS 1 and 0.25


def test_explicit_weights_are_checked_and_normalised():
    assert normalised_weights([1, 3], 2) == [0.25, 0.75]
    assert normalised_weights([], 0) == []
    for bad, match in (([1.0], "one expert weight per expert"), ([1.0, -1.0], ">= 0"),
                       ([1.0, float("inf")], ">= 0"), ([0.0, 0.0], "not all be 0"),
                       ([True, 1.0], ">= 0")):
        with pytest.raises(ValueError, match=match):
            normalised_weights(bad, 2)


def test_trainer_takes_explicit_expert_weights():
    experts = [BiasedExpert(1), RandomExpert(torch.Generator().manual_seed(0)), BiasedExpert(3)]
    trainer = Trainer(TrainConfig(**TINY), experts, [2.0, 0.0, 6.0])
    assert trainer.expert_weights.dtype == torch.float32
    assert trainer.expert_weights.tolist() == [0.25, 0.0, 0.75]
    tensor = Trainer(TrainConfig(**TINY), experts, expert_weights=torch.tensor([1.0, 1.0, 2.0]))
    assert tensor.expert_weights.tolist() == [0.25, 0.25, 0.5]
    # None: from the attributes by the QoS rule (no attributes at all: equal slices).
    assert Trainer(TrainConfig(**TINY), experts).expert_weights.tolist() == pytest.approx([1 / 3] * 3)
    assert Trainer(TrainConfig(**{**TINY, "method": "sparse"})).expert_weights is None
    for bad, match in (([1.0, 1.0], "one expert weight per expert \\(3\\)"), ([1.0, -2.0, 1.0], ">= 0"),
                       ([0.0, 0.0, 0.0], "not all be 0"), ([1.0, float("nan"), 1.0], ">= 0")):
        with pytest.raises(ValueError, match=match):
            Trainer(TrainConfig(**TINY), experts, bad)


def test_medc_train_passes_expert_weights_through():
    args = build_parser().parse_args(["--method", "medc", "--agents", "2", "--walls", "0", "--grid", "6",
                                      "--expert", "biased:1", "--expert", "biased:2",
                                      "--expert-weight", "1", "--expert-weight", "3", "--out", "unused"])
    learner = make_learner(config_from_args(args), args.expert, args.expert_weight)
    assert learner.expert_weights.tolist() == [0.25, 0.75]
    with pytest.raises(ValueError, match="one expert weight per expert"):
        make_learner(config_from_args(args), args.expert, [1.0])
