"""Benchmark episodes played through the project's evaluator (medc_training.radbench.play): the
world's readings follow the episode definition (RAD-A2C's inverse-square law, obstructions that
block the line of sight, counts from the episode's own noise stream), an episode plays the same
whatever batch it is in, and ``medc-radbench`` ends with one JSON line naming the sets' hashes."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from medc_training.cli.radbench import main
from medc_training.radbench import BenchCore, BenchSet, Episode, load_sets, paired, play_set, poisson_counts
from medc_training.radbench.scenario import noise_uniforms
from medc_training.radbench.sets import FROZEN, SETS_DIR

pytestmark = pytest.mark.usefixtures("one_thread")


def test_poisson_counts_by_inverse_cdf():
    # Poisson(2): P(X<=0) = 0.1353, P(X<=1) = 0.4060, P(X<=2) = 0.6767, P(X<=4) = 0.9473, P(X<=5) = 0.9834
    rate = torch.full((5,), 2.0)
    u = torch.tensor([0.1, 0.2, 0.5, 0.95, 0.9834], dtype=torch.float64)
    assert poisson_counts(rate, u).tolist() == [0.0, 1.0, 2.0, 5.0, 5.0]
    assert poisson_counts(torch.tensor([0.0]), torch.tensor([0.999])).item() == 0.0
    uniform = torch.from_numpy(noise_uniforms(7, 19_999, 1)[:, 0])
    for lam in (3.7, 850.0):
        counts = poisson_counts(torch.full((20_000,), lam), uniform).double()
        assert abs(counts.mean().item() - lam) < 4 * math.sqrt(lam / 20_000)
        assert counts.var().item() == pytest.approx(lam, rel=0.05)
    # The same uniform never gives fewer counts at a higher rate (common random numbers).
    low = poisson_counts(torch.full((20_000,), 40.0), uniform)
    high = poisson_counts(torch.full((20_000,), 41.0), uniform)
    assert bool((high >= low).all())


def _hand_set(episodes: list[Episode], obstructions: int) -> BenchSet:
    agents = len(episodes[0].starts)
    return BenchSet("hand", 20, 1.0, agents, 120, obstructions, "none", tuple(episodes), "0" * 64)


def test_world_rates_follow_the_inverse_square_law_and_obstructions_block_it():
    clear = Episode((0, 0), 800.0, 20, ((10, 0),), ((15, 15, 16, 16),), 11)
    blocked = Episode((0, 0), 800.0, 20, ((10, 0),), ((4, 0, 5, 3),), 12)
    on_source = Episode((0, 0), 800.0, 20, ((0, 1),), ((15, 15, 16, 16),), 13)
    core = BenchCore(_hand_set([clear, blocked, on_source], 1), [0, 1, 2])
    core.reset(seed=0)
    lay = core._take_layouts(3)
    rates = core.world_rates(lay)[:, 0]
    assert rates.tolist() == pytest.approx([800.0 / 100 + 20, 20.0, 800.0 / 1 + 20])
    lay["positions"] = lay["target"].unsqueeze(1).clone()  # on the source's own cell: d floored at 1 m
    assert core.world_rates(lay)[:, 0].tolist() == pytest.approx([820.0] * 3)
    # The first readings are the episode's own draws: inverse CDF of its noise stream at reading 0.
    u0 = torch.tensor([noise_uniforms(e.noise_seed, 120, 1)[0, 0] for e in (clear, blocked, on_source)])
    assert core.readings[:, 0].tolist() == poisson_counts(rates, u0).tolist()


def test_seven_obstructions_play_although_the_cores_own_layouts_allow_five():
    (s,) = load_sets(20, 1, obstructions=[7], snrs=["low"])
    core = BenchCore(s, [0, 1])
    core.reset(seed=0)
    assert core.attributes["walls"] == 7 and core.memory.rects.shape[1] == 7
    walls = torch.from_numpy(np.stack([s.episodes[i].walls(20) for i in (0, 1)]))
    assert torch.equal(core.walls, walls)
    assert core.positions[:, 0].tolist() == [list(s.episodes[i].starts[0]) for i in (0, 1)]


def test_an_episode_plays_the_same_in_any_batch_and_policies_pair_up():
    (s,) = load_sets(20, 3, obstructions=[2], snrs=["medium"])
    s = s.head(3)
    alone = play_set(s, "greedy", batch=1)
    together = play_set(s, "greedy", batch=3)
    assert together == alone
    for r in together:
        assert 1 <= r.length <= 120 and (r.success or r.length == 120)
        assert r.track_rmse_m is not None and r.track_rmse_m >= 0
        if r.declared_step is not None:
            assert 0 <= r.declared_step <= r.length and r.declared_error_m >= 0
    same = paired(together, alone, 120)
    assert (same["ties"], same["mean_diff"]) == (3, 0.0)
    randomly = play_set(s, "random", batch=2)
    assert [r.index for r in randomly] == [0, 1, 2]
    calls = []

    def factory(core):
        calls.append(core.num_envs)
        return None  # uniformly random moves
    play_set(s, factory, batch=2)
    assert calls == [2, 1]


def test_a_part_of_a_set_plays_its_episodes_as_the_whole_set_does():
    """Episodes 2..4 played as a part give the lines of the same episodes in the whole set: the same
    results under their own indices, the part's id."""
    (s,) = load_sets(20, 3, obstructions=[2], snrs=["medium"])
    whole = play_set(s.head(5), "greedy", batch=5)
    part = play_set(s.part(2, 3), "greedy", batch=3)
    assert [r.index for r in part] == [2, 3, 4] and {r.set_id for r in part} == {"obs2-medium[2:5]"}
    assert [(r.length, r.success, r.track_rmse_m) for r in part] == \
        [(r.length, r.success, r.track_rmse_m) for r in whole[2:]]


def test_play_refuses_what_it_cannot_play():
    (s,) = load_sets(20, 1, obstructions=[0], snrs=["low"])
    with pytest.raises(ValueError, match="unknown policy 'nonsense'"):
        play_set(s, "nonsense", episodes=1)
    with pytest.raises(Exception, match="paper-simple"):
        play_set(s, "models/experts/A1W0.safetensors", episodes=1)


def test_cli_plays_a_subset_and_ends_with_json_naming_the_hashes(capsys):
    assert main(["greedy", "random", "--obstructions", "0", "--snr", "low,high", "--episodes", "4"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    result = json.loads(out[-1])
    assert result["set_file_sha256"] == FROZEN["g20-a1.json"] and result["reference"] == "greedy"
    sets = {s.id: s for s in load_sets(20, 1, obstructions=[0], snrs=["low", "high"])}
    assert set(result["sets"]) == {"obs0-low[:4]", "obs0-high[:4]"}
    for sid, row in result["sets"].items():
        assert row["sha256"] == sets[sid.split("[")[0]].sha256
        assert set(row["policies"]) == {"greedy", "random"} and set(row["paired"]) == {"random"}
    assert set(result["pooled"]) == {"all", "obs0", "low", "high"}
    assert result["pooled"]["all"]["greedy"]["episodes"] == 8
    assert any("sha256" in line for line in out[:-1])


def test_cli_plays_a_part_of_every_set_from_first_and_its_lines_keep_the_indices(tmp_path, capsys):
    out = tmp_path / "part.jsonl"
    assert main(["greedy", "--obstructions", "0", "--snr", "low", "--first", "40", "--episodes", "3",
                 "--quiet", "--out", str(out)]) == 0
    assert set(json.loads(capsys.readouterr().out.strip().splitlines()[-1])["sets"]) == {"obs0-low[40:43]"}
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(d["set_id"], d["index"]) for d in lines] == [("obs0-low[40:43]", i) for i in (40, 41, 42)]
    assert main(["greedy", "--obstructions", "0", "--snr", "low", "--first", "200", "--quiet"]) == 2
    assert "first episode must be 0..199" in capsys.readouterr().err


def test_cli_lists_the_frozen_sets_and_refuses_a_changed_file(tmp_path, capsys):
    assert main(["--list", "--quiet"]) == 0
    listed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {k: v["sha256"] for k, v in listed["files"].items()} == FROZEN
    changed = tmp_path / "g20-a1.json"
    changed.write_text((SETS_DIR / "g20-a1.json").read_text().replace('"B":31', '"B":32', 1))
    assert main(["greedy", "--sets-file", str(changed), "--sha256", FROZEN["g20-a1.json"], "--quiet"]) == 2
    assert "was changed" in capsys.readouterr().err


def test_cost_measures_every_kind_of_policy_the_same_way(capsys, tmp_path):
    """--cost: per policy the batched evaluator at B = 1 and B = --batch, an agent node's decision,
    and the work per decision (likelihood terms of a posterior searcher, MACs of a bundle)."""
    from medc_training.bundle import save_bundle
    from medc_training.nets import make_actor_critic
    from medc_training.radbench.cost import decision_cost

    (s,) = load_sets(grid=20, agents=3, obstructions=[3], snrs=["medium"])
    team = decision_cost(s, "team-space-aware", batch=4, steps=1, node_steps=2)
    alone = decision_cost(s, "space-aware", batch=4, steps=1, node_steps=2)
    for c in (team, alone):
        assert c["b1"]["call_ms_p50"] > 0 and c["b4"]["decisions_per_s"] > 0 and c["node_ms_p50"] > 0
    # The coordinated team weighs its teammates' outcomes: more work per decision.
    assert team["likelihood_terms_per_decision"] > alone["likelihood_terms_per_decision"] > 0
    core = BenchCore(s, [0], observation="maps")
    net = make_actor_critic("lenet5", obs_shape=core.obs_shape, num_actions=8)
    manifest = {"application": "target_localization", "environment": {"grid": 20, "sensing": "realistic"}}
    bundle = save_bundle(tmp_path / "b.safetensors", net, manifest)
    learned = decision_cost(s, bundle, batch=4, steps=1, node_steps=2)
    assert learned["macs_per_decision"] > 1000 and learned["likelihood_terms_per_decision"] == 0
    assert learned["node_runtime"] == "onnxruntime"  # as an agent node runs it by default
    in_torch = decision_cost(s, bundle, batch=4, steps=1, node_steps=2, runtime="torch")
    assert in_torch["node_runtime"] == "torch" and in_torch["node_ms_p50"] > 0
    assert "node_runtime" not in team
    assert main(["--cost", "random", "greedy", "--batch", "4", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out["cost"]) == {"random", "greedy"} and out["set"] == "obs3-medium"


def test_a_bundle_at_a_temperature_samples_its_moves_and_the_lines_say_so(tmp_path, capsys):
    """--temperature T: a bundle samples from softmax(logits / T) with a seeded stream (the same
    episodes give the same moves again), 0 is the most probable move, controllers ignore it, and the
    episode lines name the temperature so a pairing keeps greedy and sampled play apart."""
    from medc_training.radbench.pairing import load_episodes

    (s,) = load_sets(20, 3, obstructions=[2], snrs=["medium"])
    s = s.head(4)
    path = tmp_path / "team" / "policy.safetensors"  # a team trained in the benchmark's world
    path.parent.mkdir()
    shutil.copy("docs/reproduction/learned-team/probes/sparse-300k/policy.safetensors", path)
    greedy = play_set(s, path)
    assert play_set(s, path, temperature=0.0) == greedy
    hot = play_set(s, path, temperature=5.0)
    assert play_set(s, path, temperature=5.0) == hot  # seeded: the same draws
    assert [r.length for r in hot] != [r.length for r in greedy]  # near-uniform draws walk otherwise
    assert play_set(s, "greedy", temperature=5.0) == play_set(s, "greedy")  # controllers unaffected
    with pytest.raises(ValueError, match="temperature must be"):
        play_set(s, path, temperature=-1.0)
    out = tmp_path / "lines.jsonl"
    assert main([str(path), "greedy", "--grid", "20", "--agents", "3", "--obstructions", "2", "--snr",
                 "medium", "--episodes", "4", "--temperature", "0.5", "--quiet", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["temperature"] == 0.5
    assert set(load_episodes([out])) == {"team@T0.5", "greedy"}


def test_out_replaces_a_link_only_when_asked_and_refuses_a_device_or_folder_first(tmp_path, capsys):
    import os
    from pathlib import Path

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    args = ["greedy", "--grid", "20", "--agents", "3", "--obstructions", "2", "--snr", "medium",
            "--episodes", "2", "--quiet", "--out"]
    for bad, words in ((Path("/dev/full"), "is not a regular file"), (tmp_path, "is a folder")):
        assert main([*args, str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("medc-radbench: ") and words in err[0], err
    assert sorted(os.listdir(tmp_path)) == ["victim.txt"]  # nothing played, no temporary file left
    out = tmp_path / "lines.jsonl"
    out.symlink_to(victim)
    assert main([*args, str(out)]) == 2  # something is there: replaced only when asked
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0], err
    assert victim.read_text() == "precious\n" and out.is_symlink()
    assert main(["--overwrite", *args, str(out)]) == 0
    assert victim.read_text() == "precious\n" and not out.is_symlink()
    assert [json.loads(line)["policy"] for line in out.read_text().splitlines()] == ["greedy", "greedy"]
    assert sorted(os.listdir(tmp_path)) == ["lines.jsonl", "victim.txt"]


def test_bundles_joined_by_plus_play_as_one_ensemble():
    """``A+B`` plays the ensemble of the two bundles; an ensemble of one bundle twice plays as that
    bundle, and a missing member is named."""
    (s,) = load_sets(20, 3, obstructions=[5], snrs=["low"])
    s = s.head(4)
    a = "docs/reproduction/learned-team/main-posterior-ft/medc-s0/policy.safetensors"
    b = "docs/reproduction/learned-team/main-posterior-hard/medc-s0/policy.safetensors"
    assert play_set(s, f"{a}+{a}") == play_set(s, a)
    both = play_set(s, f"{a}+{b}")
    assert len(both) == 4 and all(r.success or r.length == 120 for r in both)
    with pytest.raises(ValueError, match=r"no bundle at 'nowhere\.safetensors'"):
        play_set(s, f"{a}+nowhere.safetensors", episodes=1)
