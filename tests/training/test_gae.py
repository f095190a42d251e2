"""GAE on hand-computed cases: bootstrapping on truncation, never on termination."""

import pytest
import torch
from medc_training.gae import compute_gae


def _t(*values, dtype=torch.float32):
    return torch.tensor(values, dtype=dtype).unsqueeze(-1)  # [T, 1]


def test_single_step_termination_uses_reward_only():
    adv, ret = compute_gae(_t(1.0), _t(0.5), _t(10.0), _t(True, dtype=torch.bool),
                           _t(False, dtype=torch.bool),
                           gamma=0.9, gae_lambda=0.8)
    # delta = r - V(s) = 1 - 0.5; the next value (10) is ignored because the episode terminated.
    assert adv.item() == pytest.approx(0.5)
    assert ret.item() == pytest.approx(1.0)


def test_single_step_truncation_bootstraps_from_final_value():
    adv, ret = compute_gae(_t(1.0), _t(0.5), _t(10.0), _t(False, dtype=torch.bool),
                           _t(True, dtype=torch.bool),
                           gamma=0.9, gae_lambda=0.8)
    # delta = r + gamma * V(final_obs) - V(s) = 1 + 9 - 0.5
    assert adv.item() == pytest.approx(9.5)
    assert ret.item() == pytest.approx(10.0)


def test_three_steps_running_episode_hand_computed():
    g, lam = 0.9, 0.5
    rewards = _t(0.0, 1.0, 2.0)
    values = _t(1.0, 2.0, 3.0)
    next_values = _t(2.0, 3.0, 4.0)  # last one: the bootstrap value after the rollout
    no = _t(False, False, False, dtype=torch.bool)
    adv, _ = compute_gae(rewards, values, next_values, no, no, g, lam)
    d2 = 2.0 + g * 4.0 - 3.0          # 2.6
    d1 = 1.0 + g * 3.0 - 2.0          # 1.7
    d0 = 0.0 + g * 2.0 - 1.0          # 0.8
    a2 = d2
    a1 = d1 + g * lam * a2
    a0 = d0 + g * lam * a1
    assert adv.squeeze(-1).tolist() == pytest.approx([a0, a1, a2])


def test_advantage_does_not_flow_across_episode_boundary():
    g, lam = 0.99, 0.95
    rewards = _t(0.0, 5.0, 0.0)
    values = _t(1.0, 1.0, 1.0)
    next_values = _t(1.0, 0.0, 1.0)
    term = _t(False, True, False, dtype=torch.bool)
    trunc = _t(False, False, False, dtype=torch.bool)
    adv, _ = compute_gae(rewards, values, next_values, term, trunc, g, lam)
    a2 = 0.0 + g * 1.0 - 1.0
    a1 = 5.0 - 1.0                      # terminated: no bootstrap, and a2 must not leak in
    a0 = (0.0 + g * 1.0 - 1.0) + g * lam * a1
    assert adv.squeeze(-1).tolist() == pytest.approx([a0, a1, a2])


def test_truncation_and_termination_differ_only_by_the_bootstrap_term():
    kw = dict(rewards=_t(0.0, 0.0), values=_t(0.0, 0.0), next_values=_t(0.0, 3.0), gamma=0.5, gae_lambda=1.0)
    ended = _t(False, True, dtype=torch.bool)
    never = _t(False, False, dtype=torch.bool)
    term_adv, _ = compute_gae(terminated=ended, truncated=never, **kw)
    trunc_adv, _ = compute_gae(terminated=never, truncated=ended, **kw)
    assert term_adv.squeeze(-1).tolist() == pytest.approx([0.0, 0.0])
    assert trunc_adv.squeeze(-1).tolist() == pytest.approx([0.75, 1.5])


def test_shape_mismatch_is_a_clear_error():
    with pytest.raises(ValueError, match="share one shape"):
        compute_gae(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3, 1),
                    torch.zeros(3, 2, dtype=torch.bool),
                    torch.zeros(3, 2, dtype=torch.bool), 0.9, 0.9)
