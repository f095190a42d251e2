"""Where the world departs from the team's model: the benchmark's cores apply a departure to the
world's readings only, the nominal world is unchanged, and training worlds randomise per episode."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.radbench import load_sets
from medc_training.radbench.departure import Departure, jittered_positions
from medc_training.radbench.play import BenchCore, world_rates


def _core(departure=None, obstructions=5, episodes=range(12)) -> BenchCore:
    (s,) = load_sets(grid=20, agents=3, obstructions=[obstructions], snrs=["medium"])
    core = BenchCore(s, list(episodes), departure=departure)
    core.reset()
    return core


def test_parse_reads_the_cli_form_and_refuses_what_is_not_a_departure():
    d = Departure.parse("transmission=0.3, efficiency=0.7,background=80")
    assert d == Departure(transmission=0.3, efficiency=0.7, background=80.0)
    assert d.to_dict() == {"transmission": 0.3, "efficiency": 0.7, "background": 80.0}
    assert Departure.parse("").nominal and Departure.parse(None).nominal
    for bad, match in [("speed=2", "KEY=NUMBER"), ("transmission", "KEY=NUMBER"), ("efficiency=x", "number"),
                       ("transmission=1.5", r"\[0.0, 1.0\]"), ("efficiency=nan", "efficiency"),
                       ("background=-1", "background"), ("transmission=0.1,transmission=0.2", "twice")]:
        with pytest.raises(ValueError, match=match):
            Departure.parse(bad)


def test_the_nominal_world_reads_as_before():
    core = _core()
    state = core._episode_state()
    bare = {k: v for k, v in state.items() if k not in ("transmission", "efficiency")}
    rates = world_rates(core.sensing, core.cell_m, state)
    assert torch.equal(rates, world_rates(core.sensing, core.cell_m, bare))


def test_transmitting_obstructions_and_a_weaker_detector_change_the_worlds_rates_only():
    nominal, leaky = _core(), _core(Departure(transmission=0.3, efficiency=0.5))
    a, b = nominal._episode_state(), leaky._episode_state()
    rate_a, rate_b = nominal.world_rates(a), leaky.world_rates(b)
    delta = (a["positions"] - a["target"].unsqueeze(1)).float()
    inverse = 1.0 / ((delta * delta).sum(-1)).clamp(min=1.0)
    s, bg = a["strength"].unsqueeze(1), a["background"].unsqueeze(1)
    blocked = torch.isclose(rate_a, bg.expand_as(rate_a))
    assert bool(blocked.any()) and bool((~blocked).any())  # some starts behind an obstruction, some not
    want = 0.5 * torch.where(blocked, 0.3 * s * inverse + bg, rate_a)
    assert torch.allclose(rate_b, want)
    # the team's model is untouched: same sensing, same first posterior for the same readings
    assert leaky.sensing == nominal.sensing


def test_strength_and_background_departures_replace_the_episodes_levels():
    core = _core(Departure(strength_scale=2.0, background=80.0))
    plain = _core()
    assert torch.allclose(core.strength, 2.0 * plain.strength)
    assert bool((core.background == 80.0).all())


def test_position_noise_reads_at_a_free_neighbour_and_never_leaves_the_grid():
    walls = torch.zeros(1, 4, 4, dtype=torch.bool)
    walls[0, 0, 1] = True
    positions = torch.tensor([[[0, 0], [3, 3], [1, 1]]])
    for way in range(9):
        moved = jittered_positions(positions, torch.full((1, 3), way), walls)
        assert bool(((moved >= 0) & (moved < 4)).all())
        assert not bool(walls[0, moved[0, :, 0], moved[0, :, 1]].any())
        assert bool(((moved - positions).abs().amax(-1) <= 1).all())
    assert torch.equal(jittered_positions(positions, torch.zeros(1, 3, dtype=torch.long), walls), positions)
    core = _core(Departure(position_noise=1.0))
    assert core._jitter is not None and bool((core._jitter > 0).all())  # every reading is off its cell
    again = _core(Departure(position_noise=1.0))
    assert torch.equal(core._jitter, again._jitter)  # a stream of the episode: the same every time


def test_a_training_world_randomises_each_episode_within_its_ranges_and_records_it():
    options = dict(world="radbench", agents=3, walls=3, grid=20, max_steps=120, sensing="realistic", pool=24,
                   transmission_max=0.3, efficiency_spread=0.2, strength_spread=2.0, background_low=5.0,
                   background_high=80.0, position_noise_max=0.1)
    env = make_batched("target_localization", num_envs=24, seed=4, **options)
    env.reset()
    attrs = env.attributes
    for key in ("transmission_max", "efficiency_spread", "strength_spread", "background_low",
                "background_high", "position_noise_max"):
        assert attrs[key] == options[key]
    d = env._departs
    assert bool(((d["transmission"] >= 0) & (d["transmission"] <= 0.3)).all())
    assert float(d["transmission"].std()) > 0
    assert bool(((d["efficiency"] >= 0.8) & (d["efficiency"] <= 1.2)).all())
    assert bool(((env.background >= 5.0) & (env.background <= 80.0)).all())
    assert float(env.strength.min()) < 100.0 or float(env.strength.max()) > 1000.0  # outside the prior
    # the same seed draws the same departures
    twin = make_batched("target_localization", num_envs=24, seed=4, **options)
    twin.reset()
    assert all(torch.equal(twin._departs[k], d[k]) for k in d)
    nominal = make_batched("target_localization", num_envs=2, seed=4, **{k: options[k] for k in
                           ("world", "agents", "walls", "grid", "max_steps", "sensing", "pool")})
    assert "transmission_max" not in nominal.attributes


@pytest.mark.parametrize("bad, match", [({"transmission_max": 1.5}, "transmission_max"),
                                        ({"background_low": 5.0}, "together"),
                                        ({"background_low": 50.0, "background_high": 5.0}, "above"),
                                        ({"strength_spread": 0.5}, "strength_spread")])
def test_a_training_world_refuses_bad_randomisation(bad, match):
    with pytest.raises(ValueError, match=match):
        make_batched("target_localization", num_envs=1, seed=0, world="radbench", grid=20, **bad)
