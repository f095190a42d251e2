"""The cores' read-only state view (state, hold, keep_pictures): nothing outside a core writes its state."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from env_scenarios import SMALL
from medc_training.envs import make_batched
from medc_training.envs.core import EnvState
from medc_training.envs.target_localization import TargetLocalizationState


def test_state_is_a_snapshot_of_copies(name: str) -> None:
    env = make_batched(name, num_envs=2, seed=3, **SMALL[name])
    env.reset()
    state = env.state(1)
    assert isinstance(state, EnvState)
    assert state.step == 0 and len(state.positions) == env.num_agents
    assert state.positions == tuple(tuple(p) for p in env.positions[1].tolist())
    assert torch.equal(state.mask, env.mask[1])
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.step = 5
    state.mask.zero_()  # changing the snapshot does not change the env
    assert env.mask[1].any()
    moves = env.mask.float().argmax(-1)
    env.step(moves)
    assert state.step == 0 and env.state(1).step == 1  # nor does the env moving on change it
    assert env.state(1).positions != state.positions


def test_target_localization_state_has_what_a_simulator_publishes() -> None:
    env = make_batched("target_localization", num_envs=2, seed=4, noise=True, **SMALL["target_localization"])
    env.reset()
    state = env.state(0)
    assert isinstance(state, TargetLocalizationState)
    assert state.target == tuple(env.target[0].tolist())
    assert torch.equal(state.walls, env.walls[0]) and state.walls.data_ptr() != env.walls[0].data_ptr()
    assert state.readings == tuple(env.readings[0].tolist())
    state.walls.fill_(True)
    assert not env.walls[0].all()


def test_state_and_hold_need_a_reset_and_a_valid_index(name: str) -> None:
    env = make_batched(name, num_envs=2, seed=0, **SMALL[name])
    with pytest.raises(RuntimeError, match="reset"):
        env.state(0)
    with pytest.raises(RuntimeError, match="reset"):
        env.hold(0, [0])
    env.reset()
    with pytest.raises(ValueError, match=r"index must be an integer in 0\.\.1, got 2"):
        env.state(2)
    with pytest.raises(ValueError, match="agent must be an integer"):
        env.hold(0, [env.num_agents])


def test_hold_keeps_agents_in_place_for_one_step(name: str) -> None:
    env = make_batched(name, num_envs=2, seed=5, **SMALL[name])
    _, mask = env.reset()
    handed_out = mask.clone()
    before = [env.state(b).positions for b in range(2)]
    env.hold(1, [0])
    assert torch.equal(mask, handed_out)  # the mask reset() returned is left alone
    assert not env.state(1).mask[0].any() and torch.equal(env.state(0).mask, handed_out[0])
    out = env.step(handed_out.float().argmax(-1))  # every agent is given an allowed move
    after = env.state(1).positions
    assert after[0] == before[1][0]  # held: stayed
    assert after[1:] != before[1][1:]  # the others moved
    assert env.state(0).positions != before[0]
    assert out.mask[1, 0].any()  # the hold lasted one step


def test_keep_pictures_is_asked_for_not_written(name: str) -> None:
    env = make_batched(name, num_envs=1, seed=0, **SMALL[name])
    assert env.keep_final_pictures is False
    with pytest.raises(AttributeError):
        env.keep_final_pictures = True
    env.keep_pictures()
    assert env.keep_final_pictures is True
    env.keep_pictures(False)
    assert env.keep_final_pictures is False
    with pytest.raises(ValueError, match="keep must be True or False"):
        env.keep_pictures("yes")
