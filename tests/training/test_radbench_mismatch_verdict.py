"""The mismatch sweep's verdict (medc_training.radbench.mismatch_verdict) on episode lines whose
answers are worked out by hand."""

from __future__ import annotations

import json

import pytest
from medc_training.radbench.mismatch_verdict import load_sweep, main, mismatch_verdict


def _write(folder, world, rows):
    """rows: {policy: [(length, success), ...]}, one episode of set obs0-low per entry."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"{world}.episodes.jsonl", "w") as fh:
        for policy, episodes in rows.items():
            for index, (length, success) in enumerate(episodes):
                fh.write(json.dumps({"policy": policy, "grid": 20, "agents": 3, "run": 0,
                                     "set_sha256": "h", "set_id": "obs0-low[:4]", "index": index,
                                     "length": length, "success": success, "declared_step": None,
                                     "declared_error_m": None, "track_rmse_m": None}) + "\n")


def _sweep(tmp_path, learned_far):
    """A searcher at 10 moves nominally and 20 (2x, all found) under background-80; a learned team at
    8 nominally and ``learned_far`` under it (all found); under efficiency-1.3 the searcher holds
    (11, 1.1x), so that world is a measurement."""
    s, lt = tmp_path / "searchers", tmp_path / "learned"
    _write(s, "nominal", {"infotaxis": [(10, True)] * 4})
    _write(s, "background-80", {"infotaxis": [(20, True)] * 4})
    _write(s, "efficiency-1.3", {"infotaxis": [(11, True)] * 4})
    _write(lt, "nominal", {"docs/x/medc-s0/policy.safetensors": [(8, True)] * 4})
    _write(lt, "background-80", {"docs/x/medc-s0/policy.safetensors": [(learned_far, True)] * 4})
    _write(lt, "efficiency-1.3", {"docs/x/medc-s0/policy.safetensors": [(30, True)] * 4})
    return s, lt


def test_a_team_within_ten_percent_where_the_searcher_loses_meets_the_goal(tmp_path):
    s, lt = _sweep(tmp_path, learned_far=8.8)  # 1.10x its nominal 8, the bound itself
    v = mismatch_verdict(load_sweep([s, f"dr={lt}"]), ["infotaxis"], reference="infotaxis")
    assert v["learned"] == ["dr:medc-s0"]
    assert v["judged"] == ["background-80"]  # efficiency-1.3: the searcher is at 1.1x, no verdict
    row = v["worlds"]["background-80"]["policies"]["dr:medc-s0"]
    assert row["ratio"] == pytest.approx(1.1)
    assert row["vs_reference"]["mean"] == pytest.approx(8.8 - 20)
    assert v["worlds"]["background-80"]["held"] == {"dr:medc-s0": True}
    assert "held" not in v["worlds"]["efficiency-1.3"]  # 30 moves there (3.75x) is a measurement only
    assert v["goal_met"] is True


def test_a_team_past_the_bound_or_short_of_completion_does_not(tmp_path):
    s, lt = _sweep(tmp_path, learned_far=9)  # 1.125x
    assert mismatch_verdict(load_sweep([s, lt]), ["infotaxis"])["goal_met"] is False
    # Within the bound by length but one episode of four failed at the limit (75% < 95%):
    _write(lt, "background-80", {"docs/x/medc-s0/policy.safetensors": [(8, True)] * 3 + [(120, False)]})
    v = mismatch_verdict(load_sweep([s, lt]), ["infotaxis"])
    assert v["worlds"]["background-80"]["policies"]["medc-s0"]["completion"] == pytest.approx(0.75)
    assert v["goal_met"] is False


def test_no_departure_where_a_searcher_loses_gives_no_verdict(tmp_path):
    s, lt = _sweep(tmp_path, learned_far=8)
    _write(s, "background-80", {"infotaxis": [(12, True)] * 4})  # 1.2x: not a loss of 25%
    v = mismatch_verdict(load_sweep([s, lt]), ["infotaxis"])
    assert v["judged"] == [] and v["goal_met"] is False


def test_missing_worlds_policies_and_folders_are_refused_with_a_clear_message(tmp_path, capsys):
    s, lt = _sweep(tmp_path, learned_far=8)
    (lt / "efficiency-1.3.episodes.jsonl").unlink()
    with pytest.raises(ValueError, match=r"efficiency-1\.3 world was not played by medc-s0"):
        mismatch_verdict(load_sweep([s, lt]), ["infotaxis"])
    with pytest.raises(ValueError, match="no learned policy"):
        mismatch_verdict(load_sweep([s]), ["infotaxis"])
    with pytest.raises(ValueError, match="no nominal"):
        load_sweep([tmp_path])
    assert main([str(tmp_path / "absent"), "--searchers", "infotaxis"]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_the_command_prints_the_table_and_a_json_line_last(tmp_path, capsys):
    s, lt = _sweep(tmp_path, learned_far=8.8)
    assert main([str(s), str(lt), "--searchers", "infotaxis", "--reference", "infotaxis"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1])["goal_met"] is True
    assert any("searchers losing >= 1.25x: infotaxis -> medc-s0 held" in line for line in out)


def test_judge_takes_one_labelled_team_and_shows_the_others_beside_it(tmp_path, capsys):
    s, lt = _sweep(tmp_path, learned_far=9)  # past the bound
    good = tmp_path / "good"
    _write(good, "nominal", {"docs/y/medc-s0/policy.safetensors": [(8, True)] * 4})
    _write(good, "background-80", {"docs/y/medc-s0/policy.safetensors": [(8.4, True)] * 4})
    _write(good, "efficiency-1.3", {"docs/y/medc-s0/policy.safetensors": [(8, True)] * 4})
    sweep = load_sweep([s, f"old={lt}", f"new={good}"])
    assert mismatch_verdict(sweep, ["infotaxis"])["goal_met"] is False  # both judged: old fails
    v = mismatch_verdict(sweep, ["infotaxis"], judge="new")
    assert v["judged_policies"] == ["new:medc-s0"] and v["learned"] == ["new:medc-s0", "old:medc-s0"]
    assert v["worlds"]["background-80"]["held"] == {"new:medc-s0": True} and v["goal_met"] is True
    assert "old:medc-s0" in v["worlds"]["background-80"]["policies"]  # still shown
    with pytest.raises(ValueError, match="no learned policy is labelled 'other'"):
        mismatch_verdict(sweep, ["infotaxis"], judge="other")
    assert main([str(s), f"old={lt}", f"new={good}", "--searchers", "infotaxis", "--judge", "new"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["goal_met"] is True
