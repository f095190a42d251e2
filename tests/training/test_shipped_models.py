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


@pytest.mark.parametrize("grid", [20, 30])
def test_the_benchmark_teams_and_their_configs_say_how_they_were_judged(grid):
    """models/radbench/gG-a3: a bundle of the benchmark's world (3 agents, G x G, up to 7
    obstructions, 120 moves) on the window-9 observation, and a launch config that plays it under
    the 16-level prior with the endgame at 0.9, taking the world from the manifest; the grid-30 bundle
    was trained under that prior and records it."""
    import yaml
    from medc_training.radbench.endgame import check_tau
    from medc_training.radbench.physics import team_sensing

    bundle = load_bundle(MODELS / "radbench" / f"g{grid}-a3.safetensors")
    env = bundle.manifest["environment"]
    assert (env["world"], env["agents"], env["grid"], env["walls"], env["max_steps"]) == \
        ("radbench", 3, grid, 7, 120)
    assert bundle.observation == "ego9+estimate+posterior" and bundle.manifest["training"]["method"] == "medc"
    config = yaml.safe_load((MODELS / "radbench" / f"g{grid}-a3.yaml").read_text())
    assert config == {"policy": f"models/radbench/g{grid}-a3.safetensors", "prior_background": "10,50,16",
                      "endgame_tau": 0.9}
    assert (MODELS.parent / config["policy"]).is_file() and check_tau(config["endgame_tau"]) == 0.9
    assert team_sensing(config["prior_background"]).levels[1] == 16
    if grid == 30:
        assert env["prior_background_levels"] == 16


def test_the_benchmark_team_plays_a_frozen_set_shorter_than_the_strongest_searcher_did():
    """On one frozen 20 x 20 set with 6 obstructions (the first 12 episodes), the shipped team with
    its config's prior and endgame completes every episode, in fewer moves in all than the committed
    `infotaxis-exact` play of the same episodes."""
    import json

    from medc_training.radbench.endgame import Endgame
    from medc_training.radbench.physics import team_sensing
    from medc_training.radbench.play import play_set
    from medc_training.radbench.sets import load_sets

    (s,) = load_sets(20, 3, obstructions=[6], snrs=["medium"])
    played = play_set(s.head(12), Endgame(load_bundle(MODELS / "radbench" / "g20-a3.safetensors"), 0.9),
                      sensing=team_sensing("10,50,16"))
    searcher = {}
    path = MODELS.parent / "docs/reproduction/radbench/searchers/g20-a3.episodes.jsonl"
    for line in path.read_text().splitlines():
        d = json.loads(line)
        if d["policy"] == "infotaxis-exact" and d["set_sha256"] == s.sha256 and d["index"] < 12:
            searcher[d["index"]] = d["length"] if d["success"] else 120
    assert len(searcher) == 12 and all(r.success for r in played)
    assert sum(r.length for r in played) < sum(searcher.values())
