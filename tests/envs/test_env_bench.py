"""`medc-bench env` runs end to end and ends with one JSON line (figures are measured, not asserted)."""

from __future__ import annotations

import json

from medc_training.cli.bench_env import SCENARIOS, main
from medc_training.envs.tl_observation import DEFAULT_OBSERVATION

TINY = ["--num-envs", "4", "--seconds", "0.1", "--rounds", "2", "--warmup-seconds", "0", "--steps", "3"]


def _run(capsys, argv: list[str]) -> tuple[list[str], dict]:
    assert main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    return lines, json.loads(lines[-1])


def test_default_run_measures_both_presets_against_maps_with_their_targets(capsys) -> None:
    lines, figures = _run(capsys, TINY)
    scenarios = figures["scenarios"]
    assert list(scenarios) == ["paper-simple_30x30", "realistic_20x20"]
    for (sensing, grid, _), r in zip(SCENARIOS, scenarios.values(), strict=True):
        assert (r["sensing"], r["grid"], r["walls"], r["num_envs"]) == (sensing, grid, 2, 4)
        assert r["observation"] == DEFAULT_OBSERVATION and r["baseline_observation"] == "maps"
        assert r["agent_steps_per_s"] > 0 and r["baseline_agent_steps_per_s"] > 0
        assert 1 <= r["timed_steps"] <= 6 and 1 <= r["baseline_timed_steps"] <= 6  # --steps caps a round
        assert r["ratio_to_baseline"] > 0
        assert r["target_agent_steps_per_s"] is None  # targets hold at B = 256 only
    assert figures["threads"] == 1
    assert sum(line.strip().startswith("round ") for line in lines) == 2 * 2
    assert any("ratio ego6+estimate / maps" in line for line in lines)


def test_every_scenario_is_measured_against_the_reference_estimator_in_the_same_run(capsys) -> None:
    lines, figures = _run(capsys, TINY)
    for r in figures["scenarios"].values():
        assert r["reference_agent_steps_per_s"] > 0 and 1 <= r["reference_timed_steps"] <= 6
        assert r["speedup_over_reference"] > 0
    assert sum("A/B fused / reference estimator" in line for line in lines) == 2
    lines, figures = _run(capsys, [*TINY, "--no-reference"])
    assert all("speedup_over_reference" not in r for r in figures["scenarios"].values())
    assert not any("reference" in line for line in lines[:-1])


def test_custom_scenario_with_sensing_and_one_by_one(capsys) -> None:
    argv = [*TINY, "--grid", "10", "--sensing", "realistic", "--one-by-one-steps", "1"]
    lines, figures = _run(capsys, argv)
    (name, r), = figures["scenarios"].items()
    assert name == "realistic_10x10" and r["sensing"] == "realistic" and r["grid"] == 10
    assert r["one_by_one_agent_steps_per_s"] > 0 and r["ratio_to_one_by_one"] > 0
    assert any("one by one through the ParallelEnv API" in line for line in lines)


def test_the_target_scenario_reports_its_target(capsys) -> None:
    """B = 256 on the realistic 20x20 scenario (one timed step of each path)."""
    lines, figures = _run(capsys, ["--sensing", "realistic", "--seconds", "0", "--rounds", "1",
                                   "--warmup", "0", "--warmup-seconds", "0"])
    r = figures["scenarios"]["realistic_20x20"]
    assert r["target_agent_steps_per_s"] == 50_000 and r["num_envs"] == 256
    assert r["meets_target"] == (r["agent_steps_per_s"] >= 50_000)
    assert (r["timed_steps"], r["baseline_timed_steps"]) == (1, 1)
    assert any("target >= 50,000" in line for line in lines)
