"""Two runs with the same seed on one device give the same weights; another seed does not; the native
kernel's thread count changes nothing."""

import pytest
import torch
from medc_training.config import TrainConfig
from medc_training.envs import tl_native
from medc_training.experts import RandomExpert
from medc_training.ppo import Trainer

TINY = dict(env="target_localization", agents=2, walls=1, grid=8, max_steps=12, num_envs=4, horizon=32,
            epochs=2, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=64, method="medc", expert_rate=0.5)


def _weights(seed):
    trainer = Trainer(TrainConfig(seed=seed, **TINY), [RandomExpert(torch.Generator().manual_seed(seed))])
    trainer.train_update()
    trainer.train_update()
    return [p.detach().clone() for p in trainer.net.parameters()]


def test_same_seed_same_weights_other_seed_differs():
    a, b, c = _weights(5), _weights(5), _weights(6)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))


def test_sampled_evaluation_is_repeatable_and_leaves_the_training_streams_alone():
    # (The paper's maps: an untrained policy on them is near-uniform in every state.)
    cfg = TrainConfig(seed=3, eval_greedy=False,
                      **{**TINY, "method": "sparse", "eval_steps": 48, "observation": "maps"})
    trainer = Trainer(cfg)
    torch.manual_seed(123)
    first = trainer.evaluate()
    after_first = torch.rand(1)
    torch.manual_seed(123)
    second = trainer.evaluate()
    assert first == second  # the evaluation's own generator restarts from the evaluation seed
    assert torch.equal(after_first, torch.rand(1))  # and the global torch stream is untouched
    # an (almost uniform) untrained policy played greedily repeats the same moves; sampled play
    # does not, so the two protocols finish different episodes
    greedy = Trainer(TrainConfig(seed=3, **{**TINY, "method": "sparse", "eval_steps": 48,
                                            "observation": "maps"})).evaluate()
    assert (greedy["episodes"], greedy["episode_length"]) != (first["episodes"], first["episode_length"])


@pytest.mark.parametrize("sensing", ["realistic", "paper-simple"])
def test_the_native_kernel_on_two_threads_trains_bit_for_bit_as_on_one(sensing, monkeypatch):
    """A short run of the default learner with each kernel call split over two threads: the same
    losses, training episodes, weights and evaluation as with the kernel on one thread."""
    monkeypatch.setattr(tl_native, "MIN_PART_WORK", 1)  # split however small the call
    assert tl_native.library() is not None  # the kernel is built on the machines that run the tests
    runs = {}
    for count in (1, 2):
        with tl_native.split(count):
            cfg = TrainConfig(seed=4, env_options={"sensing": sensing},
                              **{**TINY, "method": "sparse", "agents": 3, "grid": 11, "num_envs": 8})
            trainer = Trainer(cfg)
            losses = [trainer.train_update() for _ in range(2)]
            runs[count] = (losses, trainer.take_train_stats(), trainer.evaluate(),
                           [p.detach().clone() for p in trainer.net.parameters()])
    (losses, stats, evaluation, weights), one = runs[2], runs[1]
    assert (losses, stats, evaluation) == one[:3] and stats["episodes"] > 0
    assert all(torch.equal(x, y) for x, y in zip(weights, one[3], strict=True))
