"""The benchmark's world as a training environment (world="radbench"): fresh episodes of the
benchmark's generator, the world's readings, reproducible from a seed, named in the attributes."""

from __future__ import annotations

import math

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.radbench.scenario import MIN_START_M, snr_bin
from medc_training.radbench.world import TRAIN_SEED_BASE, BenchWorld, draw_episodes

OPTIONS = dict(world="radbench", agents=3, walls=4, grid=20, max_steps=120, sensing="realistic", pool=40)


def _world(num_envs: int = 6, seed: int = 3, **over) -> BenchWorld:
    return make_batched("target_localization", num_envs=num_envs, seed=seed, **{**OPTIONS, **over})


def test_the_registry_of_cores_builds_it_and_its_attributes_name_the_world():
    env = _world()
    assert isinstance(env, BenchWorld)
    assert env.attributes == {"agents": 3, "walls": 4, "grid": 20, "max_steps": 120, "sensing": "realistic",
                              "world": "radbench"}
    # the manifest's attributes rebuild the same world (the evaluator's path)
    again = make_batched("target_localization", num_envs=1, seed=0, **env.attributes)
    assert isinstance(again, BenchWorld) and again.attributes == env.attributes


@pytest.mark.parametrize("bad, match", [
    ({"grid": 25}, "grids of"), ({"walls": 8}, "most obstructions"),
    ({"sensing": "paper-simple"}, "exact line of sight"), ({"noise": False}, "unknown option"),
    ({"world": "moon"}, "unknown world"),
])
def test_it_refuses_what_the_benchmark_does_not_have(bad, match):
    with pytest.raises(ValueError, match=match):
        _world(**bad)


def test_episodes_are_the_generators_mix_and_never_the_frozen_seed():
    episodes = draw_episodes(20, 3, 4, 60, TRAIN_SEED_BASE + 7)
    counts = {len(e.obstructions) for e in episodes}
    assert counts == {0, 1, 2, 3, 4}  # every count up to the most, in equal shares
    assert len(episodes) == 60
    for e in episodes:
        assert 100.0 <= e.strength < 1000.0 and 10 <= e.background <= 50
        assert min(e.dist2_m()) >= MIN_START_M ** 2 - 1e-9
    assert draw_episodes(20, 3, 4, 60, TRAIN_SEED_BASE + 7) == episodes


@pytest.fixture
def drawn(monkeypatch) -> list:
    """The episodes the training world draws for its pools from now on (a spy on draw_episodes)."""
    from medc_training.radbench import world

    seen: list = []

    def spy(*args):
        seen.extend(draw_episodes(*args))
        return draw_episodes(*args)

    monkeypatch.setattr(world, "draw_episodes", spy)
    return seen


def test_walls_min_trains_on_the_harder_counts_only_and_is_recorded(drawn):
    env = _world(walls_min=2, pool=60)
    assert env.attributes["walls_min"] == 2
    again = make_batched("target_localization", num_envs=1, seed=0, **env.attributes)
    assert again.attributes == env.attributes  # a bundle's manifest rebuilds the same mix
    drawn.clear()
    env.reset(seed=0)
    assert {len(e.obstructions) for e in drawn} == {2, 3, 4}  # the pool the world plays
    with pytest.raises(ValueError, match="walls_min"):
        _world(walls_min=5)


def test_snr_max_trains_on_the_weaker_signals_only_and_is_recorded(drawn):
    from medc_training.radbench import world

    assert "snr_max" not in _world().attributes  # the default mixes every bin and is not named
    env = _world(snr_max=0, pool=60)
    assert env.attributes["snr_max"] == 0 and "snr_max" in world.OFF_NOMINAL_OPTIONS
    again = make_batched("target_localization", num_envs=1, seed=0, **env.attributes)
    assert again.attributes == env.attributes
    mixed = {snr_bin(max(e.snrs())) for e in draw_episodes(20, 3, 4, 60, TRAIN_SEED_BASE + 7)}
    assert mixed == {"low", "medium", "high"}
    drawn.clear()
    env.reset(seed=0)
    assert drawn and {snr_bin(max(e.snrs())) for e in drawn} == {"low"}  # a set's bin: its best start
    for bad in (3, -1, True):
        with pytest.raises(ValueError, match="snr_max"):
            _world(snr_max=bad)


def test_readings_follow_the_benchmark_world():
    env = _world(num_envs=64, seed=11)
    env.reset()
    lay = env._episode_state()
    # the world's rate: S / d^2 + B with a clear line of sight, B behind an obstruction
    delta = (env.positions - env.target.unsqueeze(1)).float()
    d2 = (delta * delta).sum(-1).clamp(min=1.0)
    from medc_training.radbench.play import world_rates

    rate = world_rates(env.sensing, env.cell_m, lay)
    clear = rate > env.background.unsqueeze(1) + 1e-3
    assert torch.allclose(rate[clear], (env.strength.unsqueeze(1) / d2 + env.background.unsqueeze(1))[clear])
    assert torch.allclose(rate[~clear], env.background.unsqueeze(1).expand_as(rate)[~clear])
    # Poisson counts about that rate: the mean of many draws in one state
    draws = torch.stack([env._read(lay) for _ in range(400)])
    z = (draws.mean(0) - rate) / (rate / 400).sqrt()
    assert float(z.abs().max()) < 5.0
    assert torch.equal(draws, draws.round())


def test_a_seed_replays_the_same_episodes_and_counts():
    a, b = _world(seed=5), _world(seed=5)
    oa, _ = a.reset()
    ob, _ = b.reset()
    assert torch.equal(oa, ob) and torch.equal(a.target, b.target) and torch.equal(a.walls, b.walls)
    gen = torch.Generator().manual_seed(0)
    for _ in range(40):  # through several auto-resets and a fresh pool
        actions = torch.multinomial(a.mask.flatten(0, 1).float(), 1, generator=gen).view(a.num_envs, -1)
        sa, sb = a.step(actions), b.step(actions)
        assert torch.equal(sa.obs, sb.obs) and torch.equal(sa.reward, sb.reward)
    assert not torch.equal(_world(seed=6).reset()[0], oa)


def test_each_episode_is_played_once_before_a_fresh_pool():
    env = _world(num_envs=4, pool=15)  # 15 asked, 3 per (count, bin) group: 15 episodes
    env.reset()
    seen = []
    for _ in range(4):
        lay = env._take_layouts(4)
        pairs = zip(lay["target"], lay["strength"], strict=True)
        seen.extend((tuple(t.tolist()), float(s)) for t, s in pairs)
    assert len(set(seen[:11])) == 11  # the 4 + 11 left of the first pool are all different
    assert math.isfinite(float(env.strength.sum()))
