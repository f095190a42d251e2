"""The realistic-search study's table: the protocol's gate and verdicts from per-episode results."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from medc_lab.studies import realistic_search as study


def _write(out: Path, scenario: str, policy: str, lengths: list[int]) -> None:
    path = out / "eval" / scenario / f"{policy}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"scenario": scenario, "policy": policy, "episodes": len(lengths),
                                "seed": study.EVAL_SEED, "lengths": lengths,
                                "successes": [n < study.MAX_STEPS for n in lengths]}))


def _scenario(out: Path, name: str, learned: list[list[int]], greedy: list[int]) -> dict:
    _write(out, name, "random", [60, 100, 80, 70] * 32)
    _write(out, name, "gradient", [30, 40, 35, 45] * 32)
    _write(out, name, "greedy", greedy)
    _write(out, name, "infotaxis", [9, 10, 11, 10] * 32)
    for k, lengths in enumerate(learned):
        _write(out, name, f"learned-seed{k}", lengths)
    return next(r for r in study.summarize(out) if r["scenario"] == name)


def test_the_verdicts_follow_the_protocol(tmp_path: Path) -> None:
    fast, slow = [5, 6, 7, 6] * 32, [20, 22, 21, 23] * 32
    # The learned team beats the best controller (greedy at ~8) with disjoint CIs.
    row = _scenario(tmp_path, "g20w0", [fast, [5, 6, 6, 6] * 32, [6, 6, 7, 6] * 32], [8, 8, 9, 8] * 32)
    assert row["gate"] == "passes" and row["best_classical"] == "greedy" and row["verdict"] == "yes"
    # It learns (beats random) but is slower than the controllers.
    learned = [slow, [21, 22, 20, 22] * 32, [22, 21, 23, 20] * 32]
    row = _scenario(tmp_path, "g20w2", learned, [8, 8, 9, 8] * 32)
    assert row["gate"] == "passes" and row["verdict"] == "no"
    # Seeds that disagree: the CI over 3 seeds overlaps the best controller's.
    row = _scenario(tmp_path, "g20w5", [fast, slow, [9] * 128], [8, 9, 10, 9] * 32)
    assert row["verdict"] == "not resolved"
    # No better than random: not testable.
    row = _scenario(tmp_path, "g30w0", [[60, 100, 80, 70] * 32] * 3, [8] * 128)
    assert row["gate"] == "fails" and row["verdict"] == "not testable"
    # Missing seeds or controllers: not run.
    _write(tmp_path, "g30w2", "random", [80] * 128)
    row = next(r for r in study.summarize(tmp_path) if r["scenario"] == "g30w2")
    assert row["verdict"] == "not run"
    table = study.table_markdown(study.summarize(tmp_path))
    assert "| 20×20, 0 walls |" in table and "yes (greedy)" in table and "not testable" in table
    assert row["policies"]["random"]["length"][0] == pytest.approx(80.0)


def test_the_extension_plays_a_searcher_and_a_team_bundle(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(study, "EPISODES", 4)
    monkeypatch.setattr(study, "MAX_STEPS", 6)
    monkeypatch.setattr(study, "SCENARIOS", (study.Scenario(12, 2),))
    written = study.evaluate(tmp_path, extra=["space-aware", "team-post-ft-s0"])
    assert [p.name for p in written] == ["space-aware.json", "team-post-ft-s0.json"]
    for path in written:
        data = json.loads(path.read_text())
        assert data["scenario"] == "g12w2" and data["policy"] == path.stem and data["episodes"] == 4
        assert len(data["lengths"]) == len(data["successes"]) == 4
        assert all(1 <= n <= 6 for n in data["lengths"])
    assert not (tmp_path / "eval" / "g12w2" / "random.json").exists()  # extra alone plays no baseline


def test_the_paired_report_pairs_by_episode(tmp_path: Path) -> None:
    from medc_lab.studies import realistic_searchers as paired

    _write(tmp_path, "g20w2", "infotaxis", [10, 20, 30, 40])
    _write(tmp_path, "g20w2", "space-aware", [8, 19, 27, 38])  # differences -2, -1, -3, -2
    _write(tmp_path, "g20w2", "team-post-ft-s0", [12, 20, 30, 42])
    _write(tmp_path, "g20w2", "team-post-ft-s1", [10, 22, 30, 100])
    _write(tmp_path, "g20w2", "probe-x", [1, 1, 1, 1])
    assert paired.report(tmp_path) == {"g20w2": "space-aware"}
    row = json.loads((tmp_path / "searchers.json").read_text())["scenarios"][0]
    diff, half = row["policies"]["space-aware"]["diff"]
    assert diff == pytest.approx(-2.0)
    assert half == pytest.approx(3.182446 * (2 / 3) ** 0.5 / 2, rel=1e-3)  # t(3) * sd / sqrt(4)
    team = row["policies"]["team-post-ft (2 seeds)"]
    assert team["diff"][0] == pytest.approx((1 + 1 + 0 + 31) / 4)  # per-episode seed means minus infotaxis
    assert team["seed_spread"] == pytest.approx([26.0, 40.5])
    assert row["runner_up"] == "infotaxis" and row["shortest_vs_runner_up"][0] == pytest.approx(-2.0)
    assert "probe-x" not in row["policies"] and "learned (0 seeds)" not in row["policies"]
    page = (tmp_path / "searchers.md").read_text()
    assert "Shortest: **space-aware**, -2.00 ± 1.30 steps against infotaxis (interval excludes 0)" in page
