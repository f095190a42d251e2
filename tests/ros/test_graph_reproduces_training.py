"""Same seed + same greedy policy => the ROS graph plays the training environment's episodes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from ros_helpers import controller_reference_episodes, reference_episodes, spin_until

SCENARIO = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 11}
EPISODES = 20


@pytest.mark.timing
@pytest.mark.ros
@pytest.mark.parametrize("shared_feed", [True, False], ids=["shared-feed", "own-subscriptions"])
def test_in_process_graph_replays_training_step_for_step(graph, bundles, shared_feed):
    lengths, successes, trace = reference_episodes(bundles["a"], EPISODES, **SCENARIO)
    executor, sim, agents = graph(bundles["a"], EPISODES, shared_feed=shared_feed, **SCENARIO)
    assert spin_until(executor, lambda: sim.finished, 120), f"only {len(sim.core.results)} episodes"
    assert [r.length for r in sim.core.results] == lengths
    assert [r.success for r in sim.core.results] == successes
    assert sim.core.trace == trace  # every move of every agent, not just the lengths
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)
    assert len(set(lengths)) > 1  # the check is not trivially satisfied by all-truncated episodes


@pytest.mark.timing
@pytest.mark.ros
def test_in_process_graph_replays_training_under_realistic_sensing(graph, bundles):
    """The realistic preset end to end: the launcher takes it from the bundle's manifest and gives it
    to the simulator (Poisson counts of an unknown strength and background, walls that block the
    line of sight, success within 1.1 cells) and to every agent (its memory and source posterior):
    the graph plays the training environment's episodes, move for move."""
    scenario = {**SCENARIO, "walls": 2}
    lengths, successes, trace = reference_episodes(bundles["realistic"], 10, sensing="realistic", **scenario)
    executor, sim, agents = graph(bundles["realistic"], 10, **scenario)
    assert sim.core.sensing.name == "realistic" and sim.core.noise
    assert all(a.observer.sensing.name == a.slot.sensing == "realistic" for a in agents)
    assert spin_until(executor, lambda: sim.finished, 120), f"only {len(sim.core.results)} episodes"
    assert [r.length for r in sim.core.results] == lengths
    assert [r.success for r in sim.core.results] == successes
    assert sim.core.trace == trace
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)
    assert len(set(lengths)) > 1


@pytest.mark.timing
@pytest.mark.ros
@pytest.mark.parametrize("in_process", [False, True], ids=["processes", "launcher-in-process"])
def test_medc_launch_replays_training_episodes(bundles, tmp_path, in_process):
    lengths, successes, _ = reference_episodes(bundles["b"], EPISODES, **SCENARIO)
    config = tmp_path / "launch.yaml"
    config.write_text(json.dumps({**SCENARIO, "policy": str(bundles["b"])}))  # JSON is YAML
    launcher = Path(sys.executable).parent / "medc-launch"
    out = subprocess.run(
        [str(launcher), "--config", str(config), "--episodes", str(EPISODES), "--timeout", "150"]
        + (["--in-process"] if in_process else []),
        capture_output=True,
        text=True,
        timeout=200,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.strip().splitlines()
    assert sum(line.startswith("episode ") for line in lines) == EPISODES
    result = json.loads(lines[-1])
    assert result["episode_lengths"] == lengths
    assert result["successes"] == successes
    assert result["in_process"] is in_process


@pytest.mark.timing
@pytest.mark.ros
def test_default_launch_config_runs_infotaxis_on_the_realistic_preset(graph):
    """`medc-launch` with no config: infotaxis (the measured best team on the realistic preset) on
    RAD-A2C's 20x20 area with 2 walls and 100 steps, playing the evaluator's episodes of infotaxis."""
    from medc_bringup.launcher import load_config, resolve_policies

    episodes = 4
    cfg = load_config(None)
    assert resolve_policies(cfg) == ["infotaxis"] * 3
    assert (cfg.sensing, cfg.agents, cfg.walls, cfg.grid, cfg.max_steps) == ("realistic", 3, 2, 20, 100)
    scenario = {"agents": 3, "walls": 2, "grid": 20, "max_steps": 100, "seed": cfg.seed,
                "sensing": "realistic"}
    lengths, successes, trace = controller_reference_episodes("infotaxis", episodes, **scenario)
    executor, sim, _ = graph("infotaxis", episodes)
    assert spin_until(executor, lambda: sim.finished, 180)
    assert [r.length for r in sim.core.results] == lengths
    assert sim.core.trace == trace
    assert sum(successes) >= episodes - 1


@pytest.mark.timing
@pytest.mark.ros
def test_launch_config_with_the_shipped_team_plays_it_as_trained(graph, repo_root):
    """`medc-launch --policy models/team`: the shipped team, its manifest's scenario, training's episodes."""
    from medc_bringup.launcher import load_config, resolve_policies

    cfg = load_config(None, policy="models/team")
    team = resolve_policies(cfg)
    assert all(Path(p).parent == repo_root / "models" / "team" for p in team)
    scenario = {
        "agents": cfg.agents,
        "walls": cfg.walls,
        "grid": cfg.grid,
        "max_steps": cfg.max_steps,
        "seed": cfg.seed,
    }
    lengths, successes, trace = reference_episodes(Path(team[0]), EPISODES, **scenario)
    executor, sim, _ = graph(Path(team[0]), EPISODES, **scenario)
    assert spin_until(executor, lambda: sim.finished, 120)
    assert [r.length for r in sim.core.results] == lengths
    assert sim.core.trace == trace
    assert sum(r.success for r in sim.core.results) == sum(successes) > EPISODES // 2  # it localizes
