"""Expert.bind: every expert kind has it (the mirroring wrapper forwards it to its inner
expert), and the Trainer binds each of its experts to its environment, whatever their kind."""

from __future__ import annotations

import pytest
import torch
from medc_training.config import TrainConfig
from medc_training.experts import (
    BiasedExpert,
    Expert,
    MaliciousExpert,
    OracleExpert,
    RandomExpert,
    parse_expert,
)
from medc_training.ppo import Trainer

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=64, arch="mlp", seed=2)


class _Recorder(Expert):
    """An expert of a kind the Trainer has never heard of, recording what it is bound to."""

    name = "recorder"

    def __init__(self) -> None:
        self.bound = []

    def bind(self, env) -> _Recorder:
        self.bound.append(env)
        return self

    def scores(self, obs, mask):
        return torch.zeros(mask.shape).masked_fill(~mask, float("-inf"))


@pytest.mark.parametrize("spec", ["random", "biased:3", "oracle", "malicious:oracle", "malicious:random"])
def test_every_expert_kind_binds_and_returns_itself(spec):
    expert = parse_expert(spec)
    env = object()
    assert expert.bind(env) is expert
    oracle = expert.inner if isinstance(expert, MaliciousExpert) else expert
    if isinstance(oracle, OracleExpert):
        assert oracle.env is env  # the wrapper forwarded bind to the oracle it mirrors


def test_trainer_binds_every_expert_to_its_environment():
    wrapped, plain, recorder = MaliciousExpert(OracleExpert()), OracleExpert(), _Recorder()
    experts = [wrapped, plain, recorder, RandomExpert(torch.Generator().manual_seed(0)), BiasedExpert(1)]
    trainer = Trainer(TrainConfig(method="medc", expert_rate=1.0, **TINY), experts)
    assert wrapped.inner.env is trainer.env and plain.env is trainer.env
    assert recorder.bound == [trainer.env]
    # the bound malicious oracle advises from the training environment's state: the mirror image
    b, n, a = trainer.B, trainer.N, trainer.A
    obs = trainer.obs.reshape(b * n, *trainer.obs_shape)
    mask = trainer.mask.reshape(b * n, a)
    rows = torch.arange(b * n)
    honest = trainer.env.oracle_action_scores().reshape(b * n, a)
    mirrored = wrapped.scores_rows(obs, mask, rows)
    opposite = torch.tensor([(x + 4) % 8 for x in range(8)])
    assert torch.equal(mirrored, honest[:, opposite].masked_fill(~mask, float("-inf")))
    trainer.train_update()  # and the guided rollout runs with all of them
