"""Classical controllers (every name of controllers.CONTROLLERS) as an agent node's policy, by name.

Plain logic: an agent's decision from its TeamObserver (messages -> team memory) is the batched
core's ``controller_scores(name, env)`` argmax for that agent, step by step. Graph: a team of
controller agents plays the training environment's episodes to the end, move for move, and finds
the source; an agent started with a controller and no team size or grid refuses, saying what to pass.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from builtin_interfaces.msg import Time
from medc_agents.controller import controller_move, controller_name, own_scores, team_scores
from medc_agents.node import scenario_from_bundle
from medc_agents.policy_slot import PolicyRejected, PolicySlot
from medc_agents.team_state import TeamObserver
from medc_bringup.launcher import agent_parameters, load_config, resolve_policies
from medc_common.contract import GridGeometry
from medc_sim import messages
from medc_sim.sim_core import SimConfig, SimCore
from medc_training.controllers import CONTROLLERS, controller_scores
from medc_training.envs import make_batched
from ros_helpers import controller_reference_episodes, feed_step, spin_until

IDS = ["agent_0", "agent_1", "agent_2"]
GEO10 = GridGeometry(10, 10, 1.0)


@pytest.mark.parametrize(
    ("name", "sensing", "noise"),
    [(name, "realistic", None) for name in CONTROLLERS] + [("gradient", "paper-simple", True)],
)
def test_agent_controller_move_equals_the_batched_core(name, sensing, noise):
    """Play episodes with the controller in a SimCore and in the batched core (posterior kept), feeding
    the simulator's messages to one TeamObserver per agent: at every step each agent's controller
    move, from its own team state, is the core's controller_scores argmax for that agent (and its
    whole [1,N,8] score table equals the core's where the moves are valid)."""
    core = SimCore(SimConfig(agents=3, walls=2, grid=10, max_steps=15, seed=5, noise=bool(noise),
                             sensing=sensing))
    ref = make_batched("target_localization", num_envs=1, seed=5, agents=3, walls=2, grid=10, max_steps=15,
                       noise=noise, sensing=sensing, posterior=True)
    ref.reset()
    observers = [TeamObserver(a, 3, 10, sensing=sensing) for a in IDS]
    sec, episode, map_stamp, steps, kinds = 0, -1, None, 0, set()
    while len(core.results) < 4:
        sec += 1
        if core.episode != episode:
            episode, map_stamp = core.episode, Time(sec=sec, nanosec=1)
            for o in observers:
                o.add_map(messages.grid_msg(core.walls(), map_stamp, 1.0))
        feed_step(observers, core, Time(sec=sec), map_stamp, IDS, GEO10)
        expected = controller_scores(name, ref)  # [1,N,8]
        want = expected[0].argmax(-1).tolist()
        actions = []
        for i, o in enumerate(observers):
            assert o.ready()
            _, mask, _ = o.observe()
            assert torch.equal(mask, ref.mask[0, i])
            ours = team_scores(name, o, noise=bool(noise))
            valid = ref.mask
            assert torch.equal(ours[valid], expected[valid])
            # The agent's own row, computed alone, is the team's row i.
            assert torch.equal(own_scores(name, o, noise=bool(noise))[mask], expected[0, i][mask])
            actions.append(controller_move(name, o, mask, noise=bool(noise)))
        assert actions == want, f"step {steps}: agents chose {actions}, the core {want}"
        kinds.update(want)
        result = core.advance(actions)
        out = ref.step(torch.tensor([actions]))
        assert (result.finished is not None) == bool(out.done[0])
        if result.finished is not None:
            assert result.finished.success == bool(out.success[0])
        steps += 1
    assert steps >= 8 and len(kinds) > 1  # several steps, not one move repeated
    assert any(r.success for r in core.results)  # the controller finds the source


def test_controller_names_are_policies_without_a_manifest():
    assert [controller_name(f" {n} ") for n in CONTROLLERS] == list(CONTROLLERS)
    assert controller_name("models/team") is None and controller_name("Greedy") is None
    # No manifest: the team size and grid must be given.
    with pytest.raises(PolicyRejected, match=r"-p agents:=<n> -p grid:=<n>"):
        scenario_from_bundle("greedy", 0, 0, "")
    with pytest.raises(PolicyRejected, match=r"start the agent with -p grid:=<n>$"):
        scenario_from_bundle("infotaxis", 3, 0, "")
    assert scenario_from_bundle("gradient", 3, 10, "") == (3, 10, "")
    with pytest.raises(PolicyRejected, match="plays target_localization"):
        scenario_from_bundle("greedy", 3, 10, "", "other_application")
    slot = PolicySlot((5, 10, 10), 8, grid=10)
    assert slot.swap("greedy").description == "greedy (classical controller)"
    assert slot.controller == "greedy" and slot.current.source == "greedy"
    with pytest.raises(RuntimeError, match="decides from the team's state"):
        slot.act(torch.zeros(5, 10, 10), torch.ones(8, dtype=torch.bool))
    with pytest.raises(PolicyRejected, match="is not an existing file"):
        slot.swap("nosuchcontroller")
    assert slot.controller == "greedy"  # the old one keeps running


def test_launch_config_takes_a_controller_by_name(bundles):
    cfg = load_config(None, policy="infotaxis", agents=2, noise=True)
    assert resolve_policies(cfg) == ["infotaxis"] * 2
    # a controller has no manifest: the realistic preset's scenario (launcher.CONTROLLER_DEFAULTS)
    assert (cfg.walls, cfg.grid, cfg.max_steps, cfg.sensing) == (2, 20, 100, "realistic")
    params = agent_parameters(cfg, 1, "infotaxis")
    assert (params["policy"], params["agents"], params["grid"], params["noise"]) == ("infotaxis", 2, 20, True)
    # Mixed: a bundle team with one controller agent.
    cfg = load_config(None, policy=str(bundles["a"]), agents=3, policies={"agent_2": "gradient"})
    assert resolve_policies(cfg) == [str(bundles["a"])] * 2 + ["gradient"]


SCENARIO = {"agents": 3, "walls": 2, "grid": 10, "max_steps": 30, "seed": 11}


@pytest.mark.ros
@pytest.mark.parametrize(("name", "sensing"), [("greedy", "paper-simple"), ("infotaxis", "realistic"),
                                               ("gradient", "realistic")])
@pytest.mark.timing
def test_controller_team_plays_training_episodes_in_the_graph(graph, name, sensing):
    """medc-launch's in-process graph with policy: <controller>: every agent node runs the controller
    by name and the graph plays the evaluator's episodes of that controller, move for move, to the
    end; the team finds the source."""
    episodes = 6
    extra = {} if sensing is None else {"sensing": sensing}
    lengths, successes, trace = controller_reference_episodes(name, episodes, **SCENARIO, **extra)
    executor, sim, agents = graph(name, episodes, **SCENARIO, **extra)
    assert all(a.slot.controller == name for a in agents)
    assert spin_until(executor, lambda: sim.finished, 180), f"only {len(sim.core.results)} episodes"
    assert [r.length for r in sim.core.results] == lengths
    assert [r.success for r in sim.core.results] == successes
    assert sim.core.trace == trace
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)
    assert sum(successes) > 0


@pytest.mark.timing
@pytest.mark.ros
def test_medc_agent_with_a_controller_needs_agents_and_grid():
    agent = Path(sys.executable).parent / "medc-agent"
    out = subprocess.run([str(agent), "--ros-args", "-p", "policy:=greedy", "-p", "agents:=3"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "has no manifest to take the team size and grid from" in out.stderr
    assert "-p grid:=<n>" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.timing
@pytest.mark.ros
def test_swap_to_a_controller_by_topic_and_by_parameter(graph, bundles):
    """A running bundle team swaps to a controller by the team policy topic, and one agent to another
    controller by its parameter service: from then on every move is its controller's move for the
    team state (replayed in the batched core), the team memory of the episode kept across the swap."""
    import rclpy
    from medc_common import contract
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from ros_helpers import training_env
    from std_msgs.msg import String

    scenario = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 2}
    executor, sim, agents = graph(bundles["a"], 0, **scenario)
    operator = rclpy.create_node("operator")
    executor.add_node(operator)
    assert spin_until(executor, lambda: len(sim.core.trace) >= 5, 30)
    pub = operator.create_publisher(String, contract.team_policy_topic(contract.DEFAULT_NAMESPACE),
                                    contract.LATCHED_QOS)
    pub.publish(String(data=" greedy"))
    assert spin_until(executor, lambda: all(a.slot.controller == "greedy" for a in agents), 60)
    greedy_at = len(sim.core.trace)
    client = AsyncParameterClient(operator, "/medc/medc_agent_0")
    assert spin_until(executor, lambda: client.services_are_ready(), 60)
    future = client.set_parameters([Parameter("policy", value="infotaxis")])
    assert spin_until(executor, future.done, 60)
    result = future.result().results[0]
    assert result.successful, result.reason
    infotaxis_at = len(sim.core.trace)
    assert agents[0].slot.controller == "infotaxis" and agents[1].slot.controller == "greedy"
    assert spin_until(executor, lambda: len(sim.core.trace) >= infotaxis_at + 20, 30)
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)

    trace = list(sim.core.trace)
    ref = training_env(**scenario, posterior=True)
    ref.reset()
    checked = 0
    for i, (_, _, actions) in enumerate(trace):
        # trace[k] for k < (length when a swap was done) was decided before it; trace[length] may
        # have been decided either side of it; later steps after it.
        if i > greedy_at:
            names = ["greedy"] * 3
            names[0] = "infotaxis" if i > infotaxis_at else None if i == infotaxis_at else "greedy"
            for j, name in enumerate(names):
                if name is not None:
                    want = int(controller_scores(name, ref)[0, j].argmax())
                    assert actions[j] == want, f"step {i} agent {j}"
            checked += 1
        ref.step(torch.tensor([actions]))
    assert checked >= 20


@pytest.mark.timing
@pytest.mark.ros
def test_medc_launch_runs_a_controller_team_by_name(tmp_path):
    """`medc-launch --policy greedy`: a team of controller agents plays the evaluator's episodes."""
    import json

    episodes = 5
    lengths, successes, _ = controller_reference_episodes("greedy", episodes, **SCENARIO)
    config = tmp_path / "launch.yaml"
    config.write_text(json.dumps({**SCENARIO, "sensing": "paper-simple"}))  # JSON is YAML
    launcher = Path(sys.executable).parent / "medc-launch"
    out = subprocess.run([str(launcher), "--config", str(config), "--policy", "greedy", "--episodes",
                          str(episodes), "--in-process", "--timeout", "100"],
                         capture_output=True, text=True, timeout=150)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["config"]["policies"] == ["greedy"] * 3
    assert result["episode_lengths"] == lengths and result["successes"] == successes
    assert sum(successes) > 0


@pytest.mark.timing
@pytest.mark.ros
def test_bench_measures_a_controller_team(rclpy_context):
    from medc_bringup.bench_ros import run_graph

    r = run_graph(3, "infotaxis", in_process=True, steps=20, warmup=5, grid=10, walls=1)
    assert r["steps"] >= 20 and 0 < r["latency_ms_p50"] <= r["latency_ms_p99"] and r["dropped"] == 0
