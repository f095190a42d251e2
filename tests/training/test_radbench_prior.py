"""The team estimator's background prior on the benchmark: a training world takes it as options and
records it, a bundle trained under it plays under it (and is refused under another, in the benchmark
and in an agent node's check), and one run of ``medc-radbench`` plays every policy under one model."""

from __future__ import annotations

import json

import pytest
import torch
from medc_training.bundle import (
    BundleError,
    check_sensing,
    ensemble,
    load_bundle,
    manifest_prior,
    save_bundle,
)
from medc_training.cli.radbench import main
from medc_training.envs import make_batched
from medc_training.nets import make_actor_critic
from medc_training.radbench import load_sets
from medc_training.radbench.physics import (
    PRIOR_OPTIONS,
    TEAM_SENSING,
    background_prior,
    prior_of,
    team_sensing,
)
from medc_training.radbench.play import BenchCore, play_set, policy_sensing

WIDE = {"prior_background_low": 5.0, "prior_background_high": 100.0, "prior_background_levels": 16}


@pytest.mark.parametrize("given", ["5,100,16", " 5, 100 ,16", (5, 100, 16), [5.0, 100.0, 16.0], WIDE])
def test_a_prior_is_read_from_each_form(given):
    assert background_prior(given) == (5.0, 100.0, 16)


@pytest.mark.parametrize("given, match", [
    ("5,100", "LOW,HIGH,LEVELS"), ("5,100,x", "numbers"), ("5,100,1", "2..64"), ("5,100,16.5", "2..64"),
    ("50,5,8", "low < high"), ("0,50,8", "low < high"), ({"prior_background_low": 5.0}, "together"),
])
def test_a_malformed_prior_is_refused_saying_what_is_accepted(given, match):
    with pytest.raises(ValueError, match=match):
        background_prior(given)


def test_the_team_model_under_a_prior_changes_the_background_levels_only():
    assert background_prior({}) is None and team_sensing(None) is TEAM_SENSING
    assert prior_of(TEAM_SENSING) is None
    wide = team_sensing((5.0, 100.0, 16))
    assert wide.background == (5.0, 100.0) and wide.levels == (TEAM_SENSING.levels[0], 16)
    assert (wide.strength, wide.success_radius, wide.line, wide.name) == (
        TEAM_SENSING.strength, TEAM_SENSING.success_radius, TEAM_SENSING.line, TEAM_SENSING.name)
    assert prior_of(wide) == (5.0, 100.0, 16)
    levels = wide.background_levels()
    assert len(levels) == 16 and float(levels[0]) == pytest.approx(5 + 95 / 32) and float(levels[-1]) < 100


def test_a_training_world_takes_the_prior_and_records_it():
    env = make_batched("target_localization", num_envs=2, seed=1, world="radbench", grid=20, agents=3,
                       sensing="realistic", observation="ego6+estimate+posterior", **WIDE)
    env.reset()
    assert {k: env.attributes[k] for k in PRIOR_OPTIONS} == WIDE
    assert env.sensing.background == (5.0, 100.0) and env.sensing.levels == (6, 16)
    assert env.memory.estimator.level_background.numel() == 6 * 16
    nominal = make_batched("target_localization", num_envs=1, seed=1, world="radbench", grid=20)
    assert not set(PRIOR_OPTIONS) & set(nominal.attributes) and nominal.sensing is TEAM_SENSING
    with pytest.raises(ValueError, match="together"):
        make_batched("target_localization", num_envs=1, seed=1, world="radbench", grid=20,
                     prior_background_low=5.0)
    with pytest.raises(ValueError, match="without sensing"):
        make_batched("target_localization", num_envs=1, seed=1, world="radbench", grid=20,
                     sensing={"name": "realistic", "strength": [100.0, 1000.0], "levels": [6, 8]}, **WIDE)


def _bundles(tmp_path):
    """Two bundles of the same network on the benchmark: one recording the wide prior, one none."""
    (s,) = load_sets(grid=20, agents=3, obstructions=[3], snrs=["low"])
    core = BenchCore(s, [0], observation="maps")
    torch.manual_seed(0)
    net = make_actor_critic("lenet5", obs_shape=core.obs_shape, num_actions=8)
    env = {"grid": 20, "agents": 3, "sensing": "realistic", "world": "radbench"}
    wide = save_bundle(tmp_path / "wide.safetensors", net,
                       {"application": "target_localization", "environment": {**env, **WIDE}})
    own = save_bundle(tmp_path / "own.safetensors", net,
                      {"application": "target_localization", "environment": env})
    return s.head(3), wide, own


def test_a_bundle_plays_under_its_own_prior_and_is_refused_under_another(tmp_path):
    s, wide_path, own_path = _bundles(tmp_path)
    wide, own = load_bundle(wide_path), load_bundle(own_path)
    assert manifest_prior(wide.manifest) == (5.0, 100.0, 16) and manifest_prior(own.manifest) is None
    assert prior_of(policy_sensing(wide)) == (5.0, 100.0, 16) and policy_sensing(own) is TEAM_SENSING
    under_own_prior = play_set(s, wide_path)
    assert play_set(s, wide_path, sensing=team_sensing((5.0, 100.0, 16))) == under_own_prior
    # The same network without the prior tracks the source with another posterior.
    nominal = play_set(s, own_path)
    assert [r.track_rmse_m for r in nominal] != [r.track_rmse_m for r in under_own_prior]
    # Played deliberately under a prior it was not trained with (a probe), a bundle without one runs.
    assert [r.track_rmse_m for r in play_set(s, own_path, sensing=team_sensing((5.0, 100.0, 16)))] == \
        [r.track_rmse_m for r in under_own_prior]
    for other in (None, (5.0, 100.0, 8)):
        with pytest.raises(BundleError, match=r"background prior 5-100 counts/s at 16 levels.*"
                                              r"--prior-background 5,100,16"):
            play_set(s, wide_path, sensing=team_sensing(other))
    # An agent node checks the bundle against its sensing preset: the preset's prior is not the bundle's.
    with pytest.raises(BundleError, match="background prior 5-100"):
        check_sensing(wide.manifest, "realistic", "policy bundle P")
    check_sensing(own.manifest, "realistic")
    with pytest.raises(BundleError, match="background prior"):
        ensemble([wide, own])
    broken = {**wide.manifest, "environment": {**wide.manifest["environment"], "prior_background_levels": 1}}
    with pytest.raises(BundleError, match=r"manifest: environment: .*2\.\.64"):
        manifest_prior(broken)


def test_one_run_plays_every_policy_under_one_model(tmp_path, capsys):
    _, wide_path, own_path = _bundles(tmp_path)
    args = ["--grid", "20", "--agents", "3", "--obstructions", "3", "--snr", "low", "--episodes", "2",
            "--quiet"]
    assert main([str(wide_path), *args[:-1]]) == 0  # a bundle alone: its own prior, said in the header
    text = capsys.readouterr().out
    assert "the estimator's background prior 5-100 counts/s at 16 levels" in text
    out = json.loads(text.strip().splitlines()[-1])
    assert out["team_sensing"]["background"] == [5.0, 100.0] and out["team_sensing"]["levels"] == [6, 16]
    for mixed in ([str(wide_path), str(own_path)], ["infotaxis", str(wide_path)]):
        assert main([*mixed, *args]) == 2
        err = capsys.readouterr().err
        assert "share the team's model" in err and "5-100 at 16" in err and "--prior-background" in err
    assert main(["infotaxis", str(own_path), str(wide_path), *args, "--prior-background", "5,100,16"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["team_sensing"]["background"] == [5.0, 100.0]
    assert main(["infotaxis", *args]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["team_sensing"] == TEAM_SENSING.to_dict()
    assert main([str(wide_path), *args, "--prior-background", "10,50,8"]) == 2
    assert "--prior-background 5,100,16" in capsys.readouterr().err
    assert main(["infotaxis", *args, "--prior-background", "5,100"]) == 2
    assert "LOW,HIGH,LEVELS" in capsys.readouterr().err
