"""check_world: a bundle trained in another world or with domain randomisation is refused where it
would run in a world at the nominal model, naming the world and the options, unless allowed."""

from __future__ import annotations

import re

import pytest
from medc_training.bundle import BundleError, check_world, read_manifest, save_bundle
from medc_training.nets import make_actor_critic
from medc_training.radbench.world import OFF_NOMINAL_OPTIONS, RANDOMISATION_OPTIONS

#: What ``medc-train --world radbench`` with every randomisation option records (the randomised
#: reproduction's, plus walls_min and snr_max).
RADBENCH_DR = {"agents": 3, "grid": 20, "walls": 7, "max_steps": 120, "sensing": "realistic",
               "world": "radbench", "transmission_max": 0.3, "efficiency_spread": 0.3,
               "strength_spread": 2.0, "background_low": 5.0, "background_high": 100.0,
               "position_noise_max": 0.2, "walls_min": 5, "snr_max": 0}


def _manifest(tmp_path, environment: dict) -> dict:
    """The manifest of a saved bundle whose environment is ``environment``."""
    net = make_actor_critic("mlp", (5, environment.get("grid", 10), environment.get("grid", 10)), 8)
    path = save_bundle(tmp_path / "b.safetensors", net, {"application": "target_localization",
                                                          "environment": environment})
    return read_manifest(path)


def test_a_grid_world_bundle_passes(tmp_path):
    check_world(_manifest(tmp_path, {"grid": 10, "agents": 3, "walls": 2}))
    check_world(_manifest(tmp_path, {"grid": 10, "world": "grid", "sensing": "realistic"}), "grid")


def test_a_bundle_of_the_benchmark_world_is_refused_in_the_grid_world(tmp_path):
    manifest = _manifest(tmp_path, {"grid": 20, "world": "radbench", "sensing": "realistic"})
    with pytest.raises(BundleError, match=r"^policy P was trained in the 'radbench' world, but it is about "
                                          r"to run in the 'grid' world .* allow_other_world true"):
        check_world(manifest, what="policy P")
    check_world(manifest, "radbench")  # its own world, nominal
    check_world(manifest, allow=True)


def test_domain_randomisation_is_refused_naming_every_option(tmp_path):
    manifest = _manifest(tmp_path, RADBENCH_DR)
    for world in ("grid", "radbench"):
        with pytest.raises(BundleError) as err:
            check_world(manifest, world)
        text = str(err.value)
        assert "trained in the 'radbench' world with " in text and "allow_other_world" in text
        for key in OFF_NOMINAL_OPTIONS:
            assert re.search(rf"\b{key}={RADBENCH_DR[key]}\b", text), key
    check_world(manifest, allow=True)
    only = _manifest(tmp_path, {"grid": 10, "strength_spread": 3.0})  # an option in the grid world
    with pytest.raises(BundleError, match=r"trained in the 'grid' world with strength_spread=3\.0, but"):
        check_world(only)


def test_the_options_refused_are_those_a_training_world_records():
    """Every attribute a randomised benchmark world records beyond the nominal one is refused."""
    from medc_training.envs import make_batched

    options = {"transmission_max": 0.2, "efficiency_spread": 0.1, "strength_spread": 1.5,
               "background_low": 5.0, "background_high": 60.0, "position_noise_max": 0.1}
    assert set(options) == set(RANDOMISATION_OPTIONS)
    world = make_batched("target_localization", num_envs=1, seed=0, world="radbench", grid=20, walls=7,
                         walls_min=3, snr_max=1, pool=4, **options)
    nominal = make_batched("target_localization", num_envs=1, seed=0, world="radbench", grid=20, pool=4)
    assert set(world.attributes) - set(nominal.attributes) == set(OFF_NOMINAL_OPTIONS)
    with pytest.raises(BundleError) as err:
        check_world({"environment": world.attributes}, "radbench")
    assert all(f"{key}=" in str(err.value) for key in OFF_NOMINAL_OPTIONS)
