"""The claims report's expert evaluation: each target-localization expert played greedily on fixed
episodes of its own environment and of the A3W2 team, cached by bundle content."""

import json

import torch
from medc_lab.report.expert_eval import evaluate_experts, expert_eval_table
from medc_training.bundle import save_bundle
from medc_training.envs.tl_observation import observation_shape
from medc_training.nets import make_actor_critic

BASE = {"grid": 13, "max_steps": 10, "env_options": {"sensing": "realistic"}}


def _expert(models, name, agents, walls):
    torch.manual_seed(agents + walls)
    net = make_actor_critic("mlp", observation_shape("ego6+estimate", BASE["grid"]), 8)
    path = models / "experts" / f"{name}.safetensors"
    path.parent.mkdir(parents=True, exist_ok=True)
    save_bundle(path, net, {"application": "target_localization", "observation": {"name": "ego6+estimate"},
                            "environment": {"agents": agents, "walls": walls, "grid": BASE["grid"],
                                            "max_steps": BASE["max_steps"], "sensing": "realistic"}})
    return path


def test_experts_play_their_own_environment_and_the_team_and_are_cached(tmp_path):
    models, out = tmp_path / "models", tmp_path / "out"
    out.mkdir()
    _expert(models, "A1W0", 1, 0)
    path = _expert(models, "A2W1", 2, 1)
    results = evaluate_experts(out, models, BASE, episodes=6, seed=5)
    assert set(results) == {"A1W0 own", "A1W0 A3W2", "A2W1 own", "A2W1 A3W2"}
    assert (results["A2W1 own"]["agents"], results["A2W1 own"]["walls"]) == (2, 1)
    for r in results.values():
        assert 1 <= r["length"] <= BASE["max_steps"] and 0.0 <= r["success"] <= 1.0
    cache = json.loads((out / "expert_eval.json").read_text())
    assert len(cache) == 4 and all(len(v["lengths"]) == 6 for v in cache.values())
    # a rebuild plays nothing new: the same numbers from the cache
    assert evaluate_experts(out, models, BASE, episodes=6, seed=5) == results
    # a re-cloned expert (other bytes) is played again
    before = path.read_bytes()
    _expert(models, "A2W1", 2, 2)
    assert path.read_bytes() != before
    evaluate_experts(out, models, BASE, episodes=6, seed=5)
    assert len(json.loads((out / "expert_eval.json").read_text())) == 6
    table = expert_eval_table(results, {"infotaxis": {"length": 5.0, "length_ci": 0.5, "success": 1.0}})
    assert "| expert A2W1 | own environment (A2W1) |" in table and "| infotaxis | the team (A3W2) |" in table
