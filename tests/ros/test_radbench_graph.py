"""The field benchmark's world in the ROS graph: the shipped window-9 team (models/radbench, trained
there) plays its episodes to their end with the classical endgame and a given background prior, in
one process (move for move the benchmark's training world with medc-radbench --endgame's policy) and
as medc-launch's node processes under its shipped launch config (the results arrive, the logs say
the world and the endgame)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ros_helpers import _play_traced, run_launcher, spin_until

ROOT = Path(__file__).resolve().parents[2]
#: The shipped window-9 team: environment.world radbench, 3 agents, 20x20, 7 obstructions, 120 steps.
WINDOW9 = ROOT / "models/radbench/g20-a3.safetensors"
#: Its launch config: the prior and the endgame below.
SHIPPED_CONFIG = ROOT / "models/radbench/g20-a3.yaml"
PRIOR = "10,50,16"
TAU = 0.9
EPISODES = 2


def _reference(seed: int, episodes: int):
    """(lengths, successes, trace) of ``episodes`` of the benchmark's training world as the simulator
    draws them (seed, pool), played by the window-9 team with the endgame at TAU under PRIOR, through
    the evaluator's play loop."""
    from medc_sim.sim_core import RADBENCH_POOL
    from medc_training.bundle import load_bundle
    from medc_training.envs import make_batched
    from medc_training.radbench.endgame import Endgame
    from medc_training.radbench.physics import PRIOR_OPTIONS, background_prior

    bundle = load_bundle(WINDOW9)
    env = make_batched("target_localization", world="radbench", num_envs=1, device="cpu", seed=seed, agents=3,
                       walls=7, grid=20, max_steps=120, reward_shaping=False, sensing="realistic",
                       observation=bundle.observation, pool=RADBENCH_POOL,
                       **dict(zip(PRIOR_OPTIONS, background_prior(PRIOR), strict=True)))
    return _play_traced(env, Endgame(bundle, TAU)(env), episodes, seed)


@pytest.mark.timing
@pytest.mark.ros
def test_the_window9_team_plays_the_benchmarks_world_in_the_graph_as_on_the_benchmark(graph):
    from medc_training.radbench.physics import team_sensing

    lengths, successes, trace = _reference(0, EPISODES)
    executor, sim, agents = graph(WINDOW9, EPISODES, prior_background=PRIOR, endgame_tau=TAU)
    assert type(sim.core.env).__name__ == "BenchWorld" and sim.core.config.world == "radbench"
    assert all(a.observer.world == "radbench" and a.observer.sensing == team_sensing(PRIOR) for a in agents)
    assert all(a.decider.endgame_tau == TAU for a in agents)
    assert spin_until(executor, lambda: sim.finished, 240), f"only {len(sim.core.results)} episodes"
    assert [r.length for r in sim.core.results] == lengths
    assert [r.success for r in sim.core.results] == successes
    assert sim.core.trace == trace  # every move of every agent, the endgame's included
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)
    assert sum(a.decider.planned for a in agents) > 0  # the endgame took some of the moves


@pytest.mark.timing
@pytest.mark.ros
def test_medc_launch_runs_the_shipped_team_from_its_config_alone(tmp_path):
    """`medc-launch --config models/radbench/g20-a3.yaml` takes the benchmark's world from the
    bundle's manifest, starts the simulator and three agent processes in it with the endgame and the
    prior the config names, and the episode results arrive."""
    log = tmp_path / "nodes.log"
    code, out = run_launcher(["--config", str(SHIPPED_CONFIG), "--episodes", str(EPISODES),
                              "--timeout", "400"], tmp_path, 460, log)
    text = log.read_text()
    assert code == 0, text[-3000:]
    lines = out.strip().splitlines()
    assert sum(line.startswith("episode ") for line in lines) == EPISODES, out[-2000:]
    result = json.loads(lines[-1])
    assert len(result["episode_lengths"]) == EPISODES and all(0 < n <= 120 for n in result["episode_lengths"])
    assert result["config"]["world"] == "radbench" and result["config"]["endgame_tau"] == TAU
    assert "grid in the radbench world" in text
    assert text.count("radbench world, network in") == 3, text[-3000:]
    assert text.count(f"classical endgame on at tau {TAU:g}") == 3
    assert text.count("background 10-50 counts/s at 16 levels") == 3
