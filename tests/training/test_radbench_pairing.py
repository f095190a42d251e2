"""Policies from different medc-radbench runs paired by episode (medc_training.radbench.pairing)."""

from __future__ import annotations

import gzip
import json

import pytest
from medc_training.radbench.pairing import load_episodes, main, obstructions, pair_table


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


def test_splits_by_snr_bin_and_names_bundles_of_same_named_runs_apart(tmp_path, capsys):
    _lines(tmp_path / "a.jsonl", "probes/one/medc-s0/policy.safetensors", [(10, 12), (20, 30)])
    _lines(tmp_path / "b.jsonl", "probes/two/medc-s0/policy.safetensors", [(8, 12), (16, 25)])
    files = [tmp_path / "a.jsonl", tmp_path / "b.jsonl"]
    with pytest.raises(ValueError, match="twice"):  # one folder name for both: the same policy
        load_episodes(files)
    table = pair_table(load_episodes(files, parents=2), "one/medc-s0", by_snr=True)
    groups = table["groups"]
    assert groups["all/high"]["two/medc-s0"]["paired"]["mean_diff"] == pytest.approx((-4 - 5) / 2)
    assert groups["obs5-7/high"]["two/medc-s0"]["summary"]["episodes"] == 2
    assert groups["obs0-2/low"]["two/medc-s0"]["paired"]["mean_diff"] == pytest.approx(-1.0)
    assert "obs0-2/high" not in groups
    assert main(["--reference", "one/medc-s0", "--by-snr", "--parents", "2", *map(str, files)]) == 0
    assert "all/low:" in capsys.readouterr().out
    assert main(["--reference", "one/medc-s0", "--parents", "0", *map(str, files)]) == 2
    zipped = tmp_path / "b.jsonl.gz"  # a gzipped file of episode lines reads the same
    zipped.write_bytes(gzip.compress((tmp_path / "b.jsonl").read_bytes()))
    assert load_episodes([zipped], parents=2) == load_episodes([files[1]], parents=2)


def test_a_set_id_names_its_obstruction_count_and_snr_bin():
    assert obstructions("obs5-low[:40]") == 5 and obstructions("obs12-high") == 12
    for bad in ("obstacles5-low", "obs-low", "obs5", "5-low"):
        with pytest.raises(ValueError, match="obsN-BIN"):
            obstructions(bad)
