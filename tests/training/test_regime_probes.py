"""The claims protocol's regime probes: fixed episodes, resumable files, a readable table."""

from __future__ import annotations

import json

import pytest
from medc_lab.cli import regimes as regimes_cli
from medc_lab.studies import regime_probes as rp


def test_regime_names_round_trip_and_bad_ones_are_refused():
    assert rp.parse_regime("g40w2t50") == rp.Regime(40, 2, 50)
    assert rp.parse_regime(rp.Regime(8, 1, 12).name) == rp.Regime(8, 1, 12)
    with pytest.raises(ValueError, match="g<grid>w<walls>t<max steps>"):
        rp.parse_regime("40x40")


def test_play_writes_every_episode_and_skips_finished_files(tmp_path, capsys):
    argv = ["play", "--out", str(tmp_path), "--regime", "g8w1t12", "--policy", "random", "--policy", "greedy",
            "--episodes", "6"]
    assert regimes_cli.main(argv) == 0
    random_rec = json.loads((tmp_path / "g8w1t12" / "random.json").read_text())
    greedy_rec = json.loads((tmp_path / "g8w1t12" / "greedy.json").read_text())
    for rec in (random_rec, greedy_rec):
        assert len(rec["lengths"]) == len(rec["successes"]) == 6
        assert all(1 <= x <= 12 for x in rec["lengths"])
        # An episode that did not succeed ran to the step limit: no episode is cut short.
        assert all(ok or x == 12 for x, ok in zip(rec["lengths"], rec["successes"]))
    # The greedy walk down the posterior finds the source at least as often as random moves here.
    assert sum(greedy_rec["successes"]) >= sum(random_rec["successes"])
    capsys.readouterr()
    assert regimes_cli.main(argv) == 0  # finished: nothing is played again
    assert capsys.readouterr().out == ""
    assert regimes_cli.main(["report", "--out", str(tmp_path), "--regime", "g8w1t12", "--policy", "random",
                    "--policy", "infotaxis"]) == 0
    table = capsys.readouterr().out
    assert "| g8w1t12 |" in table and "not run" in table
