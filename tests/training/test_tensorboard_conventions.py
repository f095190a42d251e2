"""TensorBoard tags mean what CleanRL's mean: training episodes under charts/ (episodic_return,
episodic_length), the fixed-episode evaluation under eval/, the learning rate and the value
head's explained variance."""

from __future__ import annotations

import math

import numpy as np
from medc_training.config import TrainConfig
from medc_training.metrics import read_metrics
from medc_training.ppo import Trainer
from medc_training.runner import run_training

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_every=32, eval_steps=16, eval_envs=4, eval_episodes=4, seed=3)


def _scalars(tb_dir) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb_dir))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_cleanrl_tags_and_their_meanings(tmp_path):
    cfg = TrainConfig(total_steps=128, lr=3e-4, **TINY)
    run_training(Trainer(cfg), cfg, tmp_path, tensorboard=True)
    tags = _scalars(tmp_path / "tb")
    for tag in ("charts/episodic_return", "charts/episodic_length", "charts/success_rate",
                "charts/learning_rate", "charts/SPS",
                "eval/episodic_length", "eval/success_rate", "eval/episodic_return",
                "losses/explained_variance", "losses/value_loss", "losses/policy_loss", "losses/entropy"):
        assert tag in tags, f"{tag} missing; have {sorted(tags)}"
    assert "charts/train_episodic_length" not in tags  # the old name of the training episodes
    rows = {int(r["step"]): r for r in read_metrics(tmp_path / "metrics.csv")}
    # eval/ is the fixed-episode evaluation, charts/ the training episodes: the CSV's two sets.
    for step, value in tags["eval/episodic_length"]:
        assert value == rol(rows[step]["episode_length"])
    for step, value in tags["charts/episodic_length"]:
        assert value == rol(rows[step]["train_episode_length"])
    assert all(value == rol(3e-4) for _, value in tags["charts/learning_rate"])
    assert all(value <= 1.0 for _, value in tags["losses/explained_variance"])
    # Before any training episode ended nothing is reported: no placeholder length at step 0.
    assert math.isnan(rows[0]["train_episode_length"]) and math.isnan(rows[0]["train_success_rate"])
    assert 0 not in {step for step, _ in tags["charts/episodic_length"]}
    # charts/SPS as CleanRL's: steps over the whole wall time since training began, evaluations
    # included, so never above the steps over the time spent in updates alone (wall_time).
    sps = dict(tags["charts/SPS"])
    assert 0 not in sps and len(sps) >= 3
    for step, value in sps.items():
        assert 0 < value <= step / rows[step]["wall_time"] * 1.001


def rol(x: float) -> float:
    """The float32 TensorBoard stores."""
    return float(np.float32(x))


def test_explained_variance_is_cleanrls_formula():
    cfg = TrainConfig(total_steps=64, **TINY)
    trainer = Trainer(cfg)
    trainer.collect()
    buf = trainer.buffer
    rl = ~buf.bc
    y, v = buf.returns[rl].double().numpy(), buf.values[rl].double().numpy()
    expected = 1.0 - np.var(y - v) / np.var(y)
    assert math.isclose(trainer.explained_variance(), expected, rel_tol=1e-9)
    buf.values.copy_(buf.returns)
    assert math.isclose(trainer.explained_variance(), 1.0)
    buf.returns.fill_(2.0)
    assert math.isnan(trainer.explained_variance())
