"""The learned-team protocol's verdicts (medc_training.radbench.verdict), on episode lines whose
answers are worked out by hand."""

from __future__ import annotations

import json
import math

import pytest
from medc_training.radbench.verdict import frozen_verdict, main, seeds_gate, steps_to_level


def _write(path, policy, rows):
    """rows: (set_id, index, length, success)."""
    with open(path, "w") as fh:
        for set_id, index, length, success in rows:
            fh.write(json.dumps({"policy": policy, "grid": 20, "agents": 3, "run": 0,
                                 "set_sha256": "h-" + set_id, "set_id": set_id, "index": index,
                                 "length": length, "success": success, "declared_step": None,
                                 "declared_error_m": None, "track_rmse_m": None}) + "\n")


def _episodes(lengths_by_count, policy="p", successes=None):
    """{key: EpisodeResult} via a file round trip is what the tool reads; in memory the same rows."""
    from medc_training.radbench.results import EpisodeResult
    out = {}
    for count, lengths in lengths_by_count.items():
        set_id = f"obs{count}-medium[:{len(lengths)}]"
        for i, length in enumerate(lengths):
            ok = True if successes is None else successes[count][i]
            out[("h-" + set_id, set_id, i, 0, "{}")] = EpisodeResult(set_id, i, length, ok, None, None, None)
    return out


YARD = {0: [10, 12, 14, 12], 5: [20, 22, 18, 20], 6: [20, 20, 20, 20]}


def test_goal_met_when_every_seed_is_well_under_the_ratio_and_no_count_is_worse():
    seeds = [_episodes({0: [10, 12, 14, 12], 5: [14, 15, 13, 14], 6: [15, 14, 15, 16]}),
             _episodes({0: [9, 12, 13, 12], 5: [15, 16, 14, 15], 6: [14, 15, 14, 15]})]
    v = frozen_verdict(_episodes(YARD), seeds)
    goal = v["goal"]
    assert goal["yardstick_mean"] == pytest.approx(20.0)
    assert goal["per_seed"][0]["mean"] == pytest.approx((14 + 15 + 13 + 14 + 15 + 14 + 15 + 16) / 8)
    assert all(p["ratio"] <= 0.85 for p in goal["per_seed"])
    # seeds pooled: per episode the seeds' mean, minus 0.85 x the yardstick's length
    a = [14, 15, 13, 14, 15, 14, 15, 16]
    b = [15, 16, 14, 15, 14, 15, 14, 15]
    expected = sum((x + y) / 2 - 0.85 * 20 for x, y in zip(a, b)) / 8
    assert goal["pooled_vs_goal"]["n"] == 8 and goal["pooled_vs_goal"]["mean"] == pytest.approx(expected)
    assert goal["pooled_vs_goal"]["hi"] < 0
    assert v["counts"]["0"]["verdict"] == "matches"  # 0.25 shorter on average, interval across 0
    assert v["counts"]["5"]["verdict"] == "beats"
    assert v["checks"]["non_inferior_at_0"] and v["goal_met"]


def test_one_seed_over_the_ratio_or_a_worse_count_fails_the_goal():
    good = _episodes({0: [10, 12, 14, 12], 5: [14, 15, 13, 14], 6: [15, 14, 15, 16]})
    slow = _episodes({0: [10, 12, 14, 12], 5: [19, 19, 18, 19], 6: [18, 19, 18, 19]})  # 0.93 x
    v = frozen_verdict(_episodes(YARD), [good, slow])
    assert not v["checks"]["every_seed_at_most_ratio"] and not v["goal_met"]
    worse_at_0 = _episodes({0: [14, 16, 17, 15], 5: [14, 15, 13, 14], 6: [15, 14, 15, 16]})
    v = frozen_verdict(_episodes(YARD), [good, worse_at_0])
    assert v["counts"]["0"]["verdict"] == "loses" and not v["checks"]["non_inferior_at_0"]
    # an interval across 0 that reaches past the margin is not resolved, and not non-inferior
    spread = _episodes({0: [4, 22, 6, 20], 5: [14, 15, 13, 14], 6: [15, 14, 15, 16]})
    v = frozen_verdict(_episodes(YARD), [spread])
    assert v["counts"]["0"]["pooled_diff"]["lo"] < 0 < 0.05 * 12 < v["counts"]["0"]["pooled_diff"]["hi"]
    assert v["counts"]["0"]["verdict"] == "not resolved" and not v["checks"]["non_inferior_at_0"]
    assert v["checks"]["every_seed_at_most_ratio"] and not v["goal_met"]


def test_failures_count_at_the_limit_and_completion_may_not_drop():
    lengths = {0: [10, 12, 14, 12], 5: [14, 15, 13, 14], 6: [15, 14, 15, 16]}
    failed = {0: [True] * 4, 5: [False, True, True, True], 6: [True] * 4}
    team = _episodes(lengths, successes=failed)
    v = frozen_verdict(_episodes(YARD), [team])
    assert v["goal"]["per_seed"][0]["mean"] == pytest.approx((120 + 15 + 13 + 14 + 15 + 14 + 15 + 16) / 8)
    assert v["goal"]["completion_diff"]["mean"] == pytest.approx(-1 / 8)
    assert not v["checks"]["completion_no_lower"] and not v["goal_met"]


def test_refuses_nothing_to_compare():
    with pytest.raises(ValueError, match="no learned team"):
        frozen_verdict(_episodes(YARD), [])
    with pytest.raises(ValueError, match="share no episode"):
        frozen_verdict(_episodes(YARD), [_episodes({3: [10]})])


def _run(folder, seed, curve, reference_length=20):
    """A run folder whose piece bundles played 4 validation episodes at the given mean lengths."""
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"config": {"seed": seed}, "steps": 0}))
    for steps, length in curve:
        _write(folder / f"validation-{steps}.episodes.jsonl", folder.name,
               [("obs1-low[:4]", i, length, True) for i in range(4)])
        (folder / f"validation-{steps}.json").write_text("{}")
    return folder


def test_steps_to_the_yardstick_and_the_claim(tmp_path):
    yard = tmp_path / "searchers.jsonl"
    _write(yard, "infotaxis-exact", [("obs1-low[:4]", i, 20, True) for i in range(4)])
    from medc_training.radbench.pairing import load_episodes
    reference = load_episodes([yard])["infotaxis-exact"]
    runs = {"medc": [_run(tmp_path / f"m{s}", s, [(300, 25), (600, 20)]) for s in range(3)],
            "sparse": [_run(tmp_path / f"s{s}", s, [(300, 30), (600, 24), (900, 19 + s)]) for s in range(3)],
            "il": [_run(tmp_path / f"i{s}", s, [(300, 30 - 12 * (s == 0))]) for s in range(3)]}
    # a play still under way (no summary yet) does not count, even when it looks good so far
    _write(tmp_path / "m0" / "validation-100.episodes.jsonl", "m0", [("obs1-low[:4]", 0, 10, True)])
    v = steps_to_level(reference, runs, budget=900)
    assert [p["steps"] for p in v["runs"]["medc"][0]["curve"]] == [300, 600]
    assert v["runs"]["medc"][1]["reached"] == 600
    # sparse seed 2 ends at 21 > 20: censored at the budget
    assert v["runs"]["sparse"][0]["reached"] == 900 and v["runs"]["sparse"][2]["censored"]
    sparse = v["claims"]["sparse"]
    assert sparse["first_on_every_seed"] and sparse["log_ratio"]["mean"] == pytest.approx(math.log(1.5))
    assert sparse["verdict"] == "supported"  # the same ratio on every seed: a point interval above 0
    il = v["claims"]["il"]  # il's seed 0 reached the level at 300 steps, before MEDC
    assert not il["first_on_every_seed"] and il["verdict"] == "not resolved"


def test_command_line(tmp_path, capsys):
    yard = tmp_path / "yard.jsonl"
    _write(yard, "infotaxis-exact", [("obs5-low[:2]", 0, 20, True), ("obs5-low[:2]", 1, 20, True),
                                     ("obs0-low[:2]", 0, 10, True), ("obs0-low[:2]", 1, 12, True)])
    team = tmp_path / "team.jsonl"
    _write(team, "runs/sparse-s0/policy.safetensors",
           [("obs5-low[:2]", 0, 15, True), ("obs5-low[:2]", 1, 16, True),
            ("obs0-low[:2]", 0, 10, True), ("obs0-low[:2]", 1, 11, True)])
    assert main(["frozen", "--yardstick", str(yard), "--reference", "infotaxis-exact", str(team)]) == 0
    out = capsys.readouterr().out
    assert "goal met" in out and json.loads(out.splitlines()[-1])["episodes"] == 4
    assert main(["frozen", "--yardstick", str(yard), "--reference", "nobody", str(team)]) == 2
    assert "holds no 'nobody'" in capsys.readouterr().err
    assert main(["steps", "--yardstick", str(yard), "--reference", "infotaxis-exact", "--budget", "10",
                 "medc"]) == 2
    assert "METHOD=RUN_FOLDER" in capsys.readouterr().err


def test_gate_pools_the_seeds_per_episode():
    old = [_episodes({0: [10, 12, 14, 12], 5: [14, 15, 13, 14]}),
           _episodes({0: [11, 12, 13, 12], 5: [15, 15, 14, 14]})]
    new = [_episodes({0: [9, 11, 13, 11], 5: [13, 14, 12, 13]}),   # one shorter everywhere
           _episodes({0: [10, 12, 11, 12], 5: [15, 13, 13, 13]})]  # 0, 0, -2, 0; 0, -2, -1, -1
    v = seeds_gate(list(zip(new, old)))
    hard = v["groups"]["obs5-7"]
    assert hard["candidate_means"] == pytest.approx([13.0, 13.5])
    assert [p["mean"] for p in hard["per_seed"]] == pytest.approx([-1.0, -1.0])
    # pooled: per episode the two seeds' differences averaged, (-1 + 0) / 2, (-1 - 2) / 2, ...
    assert hard["pooled"]["n"] == 4
    assert hard["pooled"]["mean"] == pytest.approx((-0.5 - 1.5 - 1.0 - 1.0) / 4)
    assert hard["pooled"]["hi"] < 0 and v["groups"]["all"]["pooled"]["hi"] < 0 and v["passes"]
    assert "obs3-4" not in v["groups"]  # no episode there
    # one seed longer on the hardest sets: the pooled interval reaches above 0 and the gate fails
    worse = _episodes({0: [9, 11, 13, 11], 5: [17, 15, 19, 14]})
    v = seeds_gate([(new[0], old[0]), (worse, old[1])])
    assert v["groups"]["obs5-7"]["pooled"]["hi"] > 0 and not v["passes"]
    # failures count at the limit
    failed = _episodes({0: [9, 11, 13, 11], 5: [13, 14, 12, 13]},
                       successes={0: [True] * 4, 5: [False, True, True, True]})
    v = seeds_gate([(failed, old[0])])
    assert v["groups"]["obs5-7"]["per_seed"][0]["mean"] == pytest.approx((120 - 14 - 1 - 1 - 1) / 4)
    with pytest.raises(ValueError, match="no seed"):
        seeds_gate([])
    with pytest.raises(ValueError, match="share no validation episode"):
        seeds_gate([(new[0], _episodes({3: [10]}))])


def test_gate_command_line(tmp_path, capsys):
    rows = [("obs5-low[:3]", i, 20 + i, True) for i in range(3)] + [("obs0-low[:3]", i, 10 + i, True)
                                                                    for i in range(3)]
    old, new = tmp_path / "old.jsonl", tmp_path / "new.jsonl"
    _write(old, "runs/a/medc-s0/policy.safetensors", rows)
    _write(new, "runs/b/medc-s0/policy.safetensors",
           [(set_id, i, length - 2 - i % 2, ok) for set_id, i, length, ok in rows])
    assert main(["gate", "--candidate", str(new), "--against", str(old)]) == 0
    out = capsys.readouterr().out
    assert "gate (pooled upper bound below 0 on obs5-7 and all): passes" in out
    assert json.loads(out.splitlines()[-1])["passes"] is True
    assert main(["gate", "--candidate", str(new), str(new), "--against", str(old)]) == 2
    assert "one of each per training seed" in capsys.readouterr().err
