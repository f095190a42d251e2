"""MEDC action selection: the Q-threshold rule, the roulette wheel, expert-episode draws."""

import pytest
import torch
from medc_training.config import TrainConfig
from medc_training.experts import BiasedExpert, RandomExpert
from medc_training.medc import expert_episode_draw, expert_scores_for, follow_expert, roulette_wheel
from medc_training.ppo import Trainer

ALL = torch.ones(1, 4, dtype=torch.bool)


def test_takes_expert_best_when_probable_enough():
    probs = torch.tensor([[0.1, 0.2, 0.3, 0.4]])
    scores = torch.tensor([[0.0, 3.0, 1.0, 2.0]])  # expert ranks action 1 best
    actions, followed = follow_expert(probs, scores, ALL, q=0.05)
    assert actions.tolist() == [1] and followed.tolist() == [True]


def test_skips_improbable_best_for_next_ranked():
    probs = torch.tensor([[0.5, 0.04, 0.06, 0.40]])
    scores = torch.tensor([[0.0, 3.0, 1.0, 2.0]])  # best (1) has P < Q; next is 3
    actions, _ = follow_expert(probs, scores, ALL, q=0.05)
    assert actions.tolist() == [3]


def test_probability_equal_to_q_is_eligible():
    probs = torch.tensor([[0.05, 0.95, 0.0, 0.0]])
    scores = torch.tensor([[9.0, 1.0, 0.0, 0.0]])
    actions, _ = follow_expert(probs, scores, ALL, q=0.05)
    assert actions.tolist() == [0]


def test_no_eligible_action_means_agent_samples_itself():
    probs = torch.tensor([[0.97, 0.01, 0.01, 0.01]])
    scores = torch.tensor([[float("-inf"), 3.0, 2.0, 1.0]])  # expert never suggests action 0
    actions, followed = follow_expert(probs, scores, ALL, q=0.05)
    assert actions.tolist() == [-1] and followed.tolist() == [False]


def test_invalid_moves_are_never_followed():
    probs = torch.tensor([[0.25, 0.25, 0.25, 0.25]])
    scores = torch.tensor([[0.0, 5.0, 1.0, 0.0]])
    mask = torch.tensor([[True, False, True, True]])
    actions, _ = follow_expert(probs, scores, mask, q=0.05)
    assert actions.tolist() == [2]


def test_roulette_proportions_match_weights():
    gen = torch.Generator().manual_seed(1234)
    weights = torch.tensor([0.5, 0.3, 0.2])
    draws = roulette_wheel(weights, 20_000, gen)
    freq = torch.bincount(draws, minlength=3).float() / draws.numel()
    assert freq.tolist() == pytest.approx([0.5, 0.3, 0.2], abs=0.015)


def test_roulette_never_picks_zero_weight_and_rejects_bad_weights():
    gen = torch.Generator().manual_seed(0)
    assert set(roulette_wheel(torch.tensor([0.0, 1.0]), 500, gen).tolist()) == {1}
    with pytest.raises(ValueError, match="not all 0"):
        roulette_wheel(torch.tensor([0.0, 0.0]), 3, gen)
    with pytest.raises(ValueError):
        roulette_wheel(torch.tensor([1.0, -1.0]), 3, gen)


def test_selection_weights_follow_qos_distance():
    class E(BiasedExpert):
        def __init__(self, attrs):
            super().__init__(0)
            self.attributes = attrs

    cfg = TrainConfig(method="medc", agents=3, walls=2, grid=13, max_steps=12, num_envs=2, horizon=8,
                      eval_envs=2, eval_steps=8, eval_episodes=2, total_steps=16)
    free, complex_ = E({"agents": 1, "walls": 0, "grid": 13}), E({"agents": 1, "walls": 3, "grid": 13})
    w = Trainer(cfg, [free, complex_]).expert_weights
    # D(free) = (2 + 2 + 0) / 3, D(complex) = (2 + 1 + 0) / 3: R_S ∝ 1/D -> (1/4, 1/3) normalised
    assert w.dtype == torch.float32
    assert w.tolist() == pytest.approx([3 / 7, 4 / 7], abs=1e-6)
    assert w.sum().item() == pytest.approx(1.0)


def test_expert_episode_rate():
    gen = torch.Generator().manual_seed(5)
    draws = expert_episode_draw(20_000, 0.1, gen)
    assert draws.float().mean().item() == pytest.approx(0.1, abs=0.01)


def test_each_row_is_scored_by_its_drawn_expert():
    obs = torch.zeros(4, 1, 2, 2)
    mask = torch.ones(4, 8, dtype=torch.bool)
    experts = [BiasedExpert(2), BiasedExpert(5), RandomExpert(torch.Generator().manual_seed(0))]
    rows = torch.tensor([0, 1, 3])
    choice = torch.tensor([1, 0, 1])
    scores = expert_scores_for(experts, choice, obs, mask, rows)
    assert scores.argmax(-1).tolist() == [5, 2, 5]
