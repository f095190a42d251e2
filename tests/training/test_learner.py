"""The learner protocol that the run loop drives: Trainer and FederatedGroup implement it, and
run_training refuses anything else with an error naming what it lacks."""

from __future__ import annotations

import pytest
from medc_training.config import TrainConfig
from medc_training.frl import FederatedGroup
from medc_training.learner import Learner, check_learner
from medc_training.ppo import Trainer
from medc_training.runner import run_training

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=64, arch="mlp", seed=2)


def test_trainer_and_federated_group_are_learners():
    trainer = Trainer(TrainConfig(**TINY))
    assert isinstance(trainer, Learner) and check_learner(trainer) is trainer
    assert trainer.side_names() == [] and trainer.side_evaluate() == {}
    assert trainer.evaluate() == trainer.focal.evaluate()
    users = [{"agents": 2, "walls": 0}, {"agents": 1, "walls": 0}]
    group = FederatedGroup(TrainConfig(method="frl", frl_users=users, **TINY), side_users=[1])
    assert isinstance(group, Learner) and check_learner(group) is group
    assert group.side_names() == ["A1W0"]
    assert group.evaluate() == group.focal.evaluate()
    assert set(group.side_evaluate()) == {"A1W0"}


class _HalfLearner:
    """Has the training half of a learner, not the reporting half."""

    global_step = 0
    focal = None

    def train_update(self) -> dict:
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        return None


def test_the_run_loop_refuses_what_is_not_a_learner(tmp_path):
    assert not isinstance(_HalfLearner(), Learner)
    with pytest.raises(TypeError, match="_HalfLearner is not a learner: it lacks evaluate, side_names, "
                                        "side_evaluate"):
        run_training(_HalfLearner(), TrainConfig(**TINY), tmp_path)
    with pytest.raises(TypeError, match="lacks global_step, focal, train_update, evaluate, side_names, "
                                        "side_evaluate, state_dict, load_state_dict"):
        run_training(object(), TrainConfig(**TINY), tmp_path)
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_run_loop_records_the_side_users_curves(tmp_path):
    users = [{"agents": 2, "walls": 0}, {"agents": 1, "walls": 0}]
    cfg = TrainConfig(method="frl", frl_users=users, **TINY)
    run_training(FederatedGroup(cfg, side_users=[1]), cfg, tmp_path, tensorboard=False, save_final=False)
    assert (tmp_path / "metrics.csv").exists()
    rows = (tmp_path / "metrics_A1W0.csv").read_text().splitlines()
    assert len(rows) >= 2 and rows[0].startswith("step")
