"""MEDC, IL and FRL behave as the paper describes inside the real training loop."""

import torch
from medc_training.config import TrainConfig
from medc_training.experts import BiasedExpert, RandomExpert
from medc_training.frl import FederatedGroup
from medc_training.nets import masked_logits
from medc_training.ppo import Trainer

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=10**6, arch="mlp", seed=2)


def _own_logprobs(trainer):
    buf = trainer.buffer
    flat = buf.flat()
    with torch.no_grad():
        logits, _ = trainer.net(flat["obs"])
    logp = torch.log_softmax(masked_logits(logits, flat["masks"]), -1)
    return logp.gather(-1, flat["actions"].unsqueeze(-1)).squeeze(-1), flat


def test_medc_follows_the_expert_and_stores_the_agents_own_log_prob():
    trainer = Trainer(TrainConfig(method="medc", expert_rate=1.0, **TINY), [BiasedExpert(2)])
    trainer.collect()
    own, flat = _own_logprobs(trainer)
    east_allowed = flat["masks"][:, 2]
    # Every guided step with E allowed took E (a fresh policy gives every move P >= Q)...
    assert (flat["actions"][east_allowed] == 2).all()
    # ...and the stored log-prob is log P_agent(E), not the expert's certainty (log 1 = 0).
    assert torch.allclose(flat["logprobs"], own, atol=1e-5)
    assert (flat["logprobs"][east_allowed] < -1.0).all()
    assert not flat["bc"].any()


def test_medc_skips_expert_moves_below_q():
    cfg = TrainConfig(method="medc", expert_rate=1.0, q_threshold=0.99, **TINY)
    trainer = Trainer(cfg, [BiasedExpert(2)])
    trainer.collect()
    stats = trainer.take_train_stats()
    assert stats["expert_follow_rate"] == 0.0 and stats["expert_top_rate"] == 0.0


def test_expert_top_rate_falls_when_the_policy_disagrees_with_the_expert():
    cfg = TrainConfig(method="medc", expert_rate=1.0, **TINY)
    trainer = Trainer(cfg, [RandomExpert(torch.Generator().manual_seed(0))])
    trainer.collect()
    fresh = trainer.take_train_stats()
    assert fresh["expert_follow_rate"] == 1.0 and fresh["expert_top_rate"] == 1.0
    with torch.no_grad():  # a policy certain of one move: every other move drops below Q
        trainer.net.policy.weight.zero_()
        trainer.net.policy.bias.zero_()
        trainer.net.policy.bias[4] = 20.0
    trainer.collect()
    sharp = trainer.take_train_stats()
    # A random ranking rarely puts S first; the agent still takes an eligible move (S) every
    # time, so "followed" stays 1 while the expert's own first choice is seldom taken.
    assert sharp["expert_follow_rate"] == 1.0
    assert sharp["expert_top_rate"] < 0.5


def test_il_clones_the_expert_with_bc_and_learns_its_move():
    trainer = Trainer(TrainConfig(method="il", expert_rate=1.0, lr=3e-3, **TINY), [BiasedExpert(2)])
    trainer.collect()
    _, flat = _own_logprobs(trainer)
    east_allowed = flat["masks"][:, 2]
    assert flat["bc"][east_allowed].all() and not flat["bc"][~east_allowed].any()
    before = _own_logprobs(trainer)[0][east_allowed].mean()
    for _ in range(5):
        trainer.update()
    after = _own_logprobs(trainer)[0][east_allowed].mean()
    assert after > before + 0.5, (before, after)


def test_frl_users_share_one_global_model_after_each_round():
    cfg = TrainConfig(method="frl", frl_users=[{"agents": 1, "walls": 0}, {"agents": 2, "walls": 0}], **TINY)
    group = FederatedGroup(cfg)
    assert group.focal_index == 1
    group.train_update()
    a, b = (t.net.state_dict() for t in group.trainers)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert group.global_step == 32


def test_frl_malicious_user_poisons_the_average():
    users = [{"agents": 2, "walls": 0}, {"agents": 1, "walls": 0}]
    bad = [users[0], {**users[1], "fault": "malicious"}]
    honest = FederatedGroup(TrainConfig(method="frl", frl_users=users, **TINY)).focal.net.policy.weight
    poisoned = FederatedGroup(TrainConfig(method="frl", frl_users=bad, **TINY)).focal.net.policy.weight
    # User 0 starts from the same weights W0 as a lone learner with the same seed; user 1 from
    # W1. Honest FedAvg gives (W0 + W1) / 2; the malicious user sends -W1 for the policy head,
    # giving (W0 - W1) / 2, so the two averages add up to W0.
    alone = Trainer(TrainConfig(method="sparse", **TINY)).net.policy.weight
    assert torch.allclose(honest + poisoned, alone, atol=1e-6)
    assert not torch.allclose(honest, poisoned, atol=1e-4)
