"""The benchmark's markdown tables (medc_training.radbench.tables) from a real run's JSON."""

from __future__ import annotations

import json

import torch
from medc_training.cli.radbench import main
from medc_training.radbench.tables import main as tables_main
from medc_training.radbench.tables import run_tables, verdict


def test_the_paired_verdict_reads_the_interval():
    assert verdict(-2.0, 1.5) == "beats"
    assert verdict(2.0, 1.5) == "loses"
    assert verdict(-1.0, 1.5) == "not resolved"
    assert verdict(None, None) == "-"


def test_tables_of_a_run_name_every_policy_and_the_strongest_per_obstruction_count(capsys, tmp_path):
    torch.set_num_threads(1)
    args = ["random", "greedy", "--obstructions", "0,5", "--snr", "high", "--episodes", "4", "--quiet"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    text = run_tables(doc, "small")
    assert text.startswith("### small")
    rows = [line for line in text.splitlines() if line.startswith("| ")]
    assert rows[2].startswith("| random |") and "reference" in rows[2]
    greedy = doc["paired_pooled"]["all"]["greedy"]
    assert rows[3].startswith("| greedy |")
    assert verdict(greedy["mean_diff"], greedy["mean_diff_ci95"]) in rows[3]
    by_count = [r for r in rows if r.startswith("| 0 |") or r.startswith("| 5 |")]
    assert len(by_count) == 2 and all(r.count("**") == 2 for r in by_count)
    for row, count in zip(by_count, (0, 5)):
        means = {p: doc["pooled"][f"obs{count}"][p]["mean_length"] for p in ("random", "greedy")}
        assert f"**{min(means.values()):.1f}**" in row
    (tmp_path / "small.json").write_text(json.dumps(doc))
    assert tables_main([str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == text.strip()
    assert tables_main([str(tmp_path / "missing")]) == 2
