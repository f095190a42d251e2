"""Policies from different medc-radbench runs paired by episode (medc_training.radbench.pairing)."""

from __future__ import annotations

import json

import pytest
from medc_training.radbench.pairing import load_episodes, main, pair_table


def _lines(path, policy, lengths, sets=("obs0-low[:2]", "obs6-high[:2]"), run=0):
    with open(path, "w") as fh:
        for s, (a, b) in zip(sets, lengths, strict=True):
            for index, length in enumerate((a, b)):
                fh.write(json.dumps({"policy": policy, "grid": 20, "agents": 3, "run": run,
                                     "set_sha256": "h" + s,
                                     "set_id": s, "index": index, "length": length, "success": length < 120,
                                     "declared_step": None, "declared_error_m": None,
                                     "track_rmse_m": 1.0}) + "\n")


def test_pairs_runs_by_episode_and_groups_by_obstruction_count(tmp_path, capsys):
    _lines(tmp_path / "a.jsonl", "searcher", [(10, 12), (20, 30)])
    _lines(tmp_path / "b.jsonl", "runs/team/policy.safetensors", [(8, 12), (120, 25)])
    table = pair_table(load_episodes([tmp_path / "a.jsonl", tmp_path / "b.jsonl"]), "searcher")
    team = table["groups"]["all"]["team"]
    assert team["summary"]["mean_length"] == pytest.approx((8 + 12 + 120 + 25) / 4)
    assert team["paired"]["mean_diff"] == pytest.approx(((8 - 10) + 0 + (120 - 20) + (25 - 30)) / 4)
    assert table["groups"]["obs5-7"]["team"]["paired"]["mean_diff"] == pytest.approx((100 - 5) / 2)
    assert table["groups"]["obs0-2"]["team"]["summary"]["episodes"] == 2 and "obs3-4" not in table["groups"]
    assert main(["--reference", "searcher", str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl")]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["episodes"] == 4


def test_refuses_what_does_not_pair(tmp_path, capsys):
    _lines(tmp_path / "a.jsonl", "searcher", [(10, 12), (20, 30)])
    _lines(tmp_path / "b.jsonl", "team", [(8, 12), (12, 25)], run=1)  # other count noise: no common episode
    assert main(["--reference", "searcher", str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl")]) == 2
    assert "share no episode" in capsys.readouterr().err
    assert main(["--reference", "nobody", str(tmp_path / "a.jsonl")]) == 2
    (tmp_path / "bad.jsonl").write_text("{}\n")
    assert main(["--reference", "searcher", str(tmp_path / "bad.jsonl")]) == 2
    assert "not a medc-radbench episode line" in capsys.readouterr().err
