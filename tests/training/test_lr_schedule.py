"""The learning-rate schedule: constant by default, or lowered linearly to 0 at ``lr_anneal_steps``
training steps, carried on across a resume (it depends on the steps trained, not on the piece)."""

import pytest
from medc_training.config import TrainConfig
from medc_training.ppo import Trainer

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=10**6, arch="mlp", seed=2, lr=1e-3)


def test_the_learning_rate_falls_linearly_to_zero_at_the_anneal_steps_and_stays_there():
    spu = TrainConfig(**TINY).steps_per_update
    trainer = Trainer(TrainConfig(lr_anneal_steps=4 * spu, **TINY))
    rates = [trainer.train_update()["learning_rate"] for _ in range(6)]
    # The update after k rollouts runs at lr * (1 - k/4).
    assert rates == pytest.approx([1e-3 * 0.75, 1e-3 * 0.5, 1e-3 * 0.25, 0.0, 0.0, 0.0])


def test_the_default_keeps_the_learning_rate_constant():
    trainer = Trainer(TrainConfig(**TINY))
    assert [trainer.train_update()["learning_rate"] for _ in range(3)] == [1e-3] * 3


def test_a_resumed_trainer_carries_the_schedule_on():
    spu = TrainConfig(**TINY).steps_per_update
    cfg = TrainConfig(lr_anneal_steps=4 * spu, **TINY)
    first = Trainer(cfg)
    first.train_update()
    second = Trainer(cfg)
    second.load_state_dict(first.state_dict())
    assert second.train_update()["learning_rate"] == pytest.approx(1e-3 * 0.5)


def test_a_negative_anneal_horizon_is_refused():
    with pytest.raises(ValueError, match="lr_anneal_steps"):
        TrainConfig(lr_anneal_steps=-1, **TINY).validate()
