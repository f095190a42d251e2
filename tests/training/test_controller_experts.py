"""A classical search controller as an MEDC/IL expert (controller:NAME): asked only on guided steps,
only for the guided environments, and its moves are the ones the trainer takes there."""

from __future__ import annotations

import pytest
import torch
from medc_training.config import TrainConfig
from medc_training.controllers import controller_scores
from medc_training.envs import make_batched
from medc_training.experts import ControllerExpert, ExpertError, parse_expert
from medc_training.ppo import Trainer

WORLD = {"world": "radbench", "sensing": "realistic", "pool": 48}
TINY = dict(env="target_localization", agents=2, walls=3, grid=20, max_steps=120, num_envs=3, horizon=24,
            epochs=1, minibatches=2, eval_envs=2, eval_episodes=2, total_steps=48, arch="mlp", seed=5,
            observation="ego6+estimate", env_options=WORLD)


def _trainer(method: str, rate: float, name: str = "infotaxis", **over) -> tuple[Trainer, ControllerExpert]:
    expert = parse_expert(f"controller:{name}")
    trainer = Trainer(TrainConfig(method=method, expert_rate=rate, **{**TINY, **over}), [expert])
    return trainer, expert


def test_spec_names_a_controller_and_refuses_unknown_ones():
    assert isinstance(parse_expert("controller:space-aware"), ControllerExpert)
    with pytest.raises(ExpertError, match="unknown controller"):
        parse_expert("controller:telepathy")


def test_binding_refuses_a_core_without_the_posterior_the_searcher_reads():
    env = make_batched("target_localization", num_envs=1, seed=0, grid=8, walls=0, observation="maps")
    with pytest.raises(ExpertError, match="posterior"):
        parse_expert("controller:infotaxis").bind(env)


def test_il_takes_the_controllers_move_on_every_guided_step():
    trainer, expert = _trainer("il", 1.0)
    env = trainer.env
    taken: list[tuple[torch.Tensor, torch.Tensor]] = []
    step = env.step

    def recording_step(actions):
        wanted = controller_scores("infotaxis", env).argmax(-1)  # the state the trainer acted in
        taken.append((actions.clone(), wanted))
        return step(actions)

    env.step = recording_step
    trainer.collect()
    assert len(taken) == trainer.buffer.steps
    for actions, wanted in taken:
        assert torch.equal(actions, wanted)
    assert bool(trainer.buffer.bc.all())  # IL clones every guided sample
    assert expert.rows_scored == trainer.buffer.steps * trainer.B * trainer.N


def test_the_controller_is_never_asked_on_unguided_steps():
    trainer, expert = _trainer("medc", 0.0)
    trainer.collect()
    assert trainer.expert_steps == 0 and expert.rows_scored == 0


def test_medc_asks_only_for_the_guided_episodes_rows():
    trainer, expert = _trainer("medc", 0.5, num_envs=8, horizon=64)
    guided = trainer.expert_episode.clone()
    trainer.collect()
    assert 0 < int(guided.sum()) < trainer.B  # some episodes guided, some not
    assert expert.rows_scored == trainer.expert_steps * trainer.N


@pytest.mark.parametrize("name", ["infotaxis", "space-aware"])
def test_scores_for_some_rows_are_the_controllers_scores_of_those_environments(name):
    env = make_batched("target_localization", num_envs=3, seed=1, agents=2, walls=3, grid=20, max_steps=120,
                       observation="ego6+estimate", **WORLD)
    obs, mask = env.reset()
    expert = parse_expert(f"controller:{name}").bind(env)
    rows = torch.tensor([2, 3])  # the whole team of environment 1
    got = expert.scores_rows(obs.flatten(0, 1), mask.flatten(0, 1), rows)
    want = controller_scores(name, env, envs=torch.tensor([1]))[0]
    assert torch.equal(got, want)
    assert expert.attributes == env.attributes  # an exact match for the QoS rule
