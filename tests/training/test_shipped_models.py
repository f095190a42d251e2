"""The bundles shipped in models/ load, describe themselves, and the team beats random play."""

from pathlib import Path

import pytest
from medc_training.bundle import load_bundle
from medc_training.evaluate import env_for_bundle, evaluate_policy

MODELS = Path(__file__).resolve().parents[2] / "models"
TEAM = MODELS / "team" / "A3W2.safetensors"


def test_team_bundle_describes_a3w2_and_its_training():
    bundle = load_bundle(TEAM)
    env = bundle.manifest["environment"]
    assert (bundle.manifest["application"], env["agents"], env["walls"]) == ("target_localization", 3, 2)
    assert bundle.manifest["training"]["steps"] > 0
    assert TEAM.stat().st_size < 2_000_000


def test_team_clearly_beats_a_random_team():
    bundle = load_bundle(TEAM)
    team = evaluate_policy(env_for_bundle(bundle, num_envs=32, seed=7), bundle, episodes=128, greedy=True,
                           seed=7)
    rand = evaluate_policy(env_for_bundle(bundle, num_envs=32, seed=7), None, episodes=128, seed=7)
    assert team["episode_length"] < rand["episode_length"] - 4, (team, rand)
    assert team["success_rate"] > rand["success_rate"]


@pytest.mark.parametrize("path", sorted((MODELS / "experts").glob("*.safetensors")), ids=lambda p: p.stem)
def test_every_expert_loads_and_matches_its_name(path):
    bundle = load_bundle(path)
    env = bundle.manifest["environment"]
    if path.stem.startswith("A"):
        assert bundle.manifest["application"] == "target_localization"
        assert path.stem == f"A{env['agents']}W{env['walls']}"
    else:
        assert bundle.manifest["application"] in ("fleet_coordination", "maze_cleaning")
        assert path.stem.split("-")[1].startswith(f"A{env['agents']}")
    assert path.stat().st_size < 2_000_000
