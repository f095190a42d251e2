"""The field benchmark's world in the ROS graph, on its logic without spinning a node: the simulator's
core in that world (the options that do not apply to it refused), the agents' observation built from
its messages (bit for bit the benchmark's), and their moves with the classical endgame (those of
medc-radbench --endgame)."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from builtin_interfaces.msg import Time
from medc_agents.bench_team import endgame_move, team_model
from medc_agents.node import Decider
from medc_agents.policy_slot import PolicySlot
from medc_agents.team_state import TeamObserver
from medc_common.contract import GridGeometry
from medc_sim import messages
from medc_sim.sim_core import RADBENCH_POOL, SimConfig, SimCore
from medc_training.bundle import load_bundle
from medc_training.envs import make_batched
from medc_training.envs.grid import ACTIONS
from medc_training.envs.wall_cover import OBSTRUCTION_SLOTS
from medc_training.nets import masked_logits
from medc_training.radbench.endgame import Endgame
from medc_training.radbench.physics import PRIOR_OPTIONS, background_prior, team_sensing
from medc_training.radbench.play import BenchCore
from medc_training.radbench.scenario import generate_set
from medc_training.radbench.sets import BenchSet
from ros_helpers import observe_as_reference

RADBENCH = dict(world="radbench", agents=3, walls=7, grid=20, max_steps=120, sensing="realistic", seed=3)


def _within(cells, target, radius: float) -> bool:
    return any(math.dist(c, target) <= radius for c in cells)


def test_the_simulator_plays_the_benchmarks_world_from_the_cores_state():
    core = SimCore(SimConfig(**RADBENCH))
    assert type(core.env).__name__ == "BenchWorld" and core.noise and core.sensing.name == "realistic"
    gen = torch.Generator().manual_seed(1)
    obstructed = 0
    while len(core.results) < 3:
        state = core.env.state(0)
        # What the node publishes is the core's own state.
        assert core.positions() == list(state.positions) and core.readings() == list(state.readings)
        assert torch.equal(core.walls(), state.walls) and core.target() == state.target
        assert all(float(v).is_integer() and v >= 0 for v in core.readings())  # Poisson counts
        obstructed += int(core.walls().any())
        before, episode = core.positions(), core.episode
        held = int(torch.randint(0, 3, (1,), generator=gen))
        actions = [int(a) for a in torch.randint(0, 8, (3,), generator=gen)]
        actions[held] = None
        result = core.advance(actions)
        if result.finished is None:
            assert core.positions()[held] == before[held]  # a held agent stays where it is
            assert core.step == state.step + 1
        else:
            done = result.finished
            assert done.episode == episode and core.episode == episode + 1 and core.step == 0
            assert done.success == (done.ended_by == "source") and (done.truncated or done.success)
            assert done.length <= RADBENCH["max_steps"]
    assert obstructed > 0


def test_an_episode_ended_by_the_driver_starts_the_next_one():
    core = SimCore(SimConfig(**RADBENCH))
    core.advance([0, 0, 0])
    first = core.env.state(0)
    target = core.target()
    result = core.end_by_declaration(target)
    assert result.success and result.error == 0.0 and result.length == first.step
    assert core.episode == 1 and core.step == 0 and core.results == [result]
    missed = core.end_by_declaration((target[0], (target[1] + 10) % 20))
    assert not missed.success and core.episode == 2


def test_a_step_that_does_not_end_the_episode_leaves_every_uav_outside_the_success_radius():
    """The agents rule out the cells near every UAV on a step that did not end the episode, so the
    simulator must end it exactly when a UAV comes within the radius."""
    core = SimCore(SimConfig(**{**RADBENCH, "walls": 0, "grid": 20, "seed": 8}))
    gen = torch.Generator().manual_seed(4)
    ended = []
    while len(ended) < 4:
        target = core.target()
        result = core.advance([int(a) for a in torch.randint(0, 8, (3,), generator=gen)])
        if result.finished is None:
            assert not _within(core.positions(), target, core.sensing.success_radius)
        else:
            ended.append(result.finished)
    assert all(r.success != r.truncated for r in ended)


@pytest.mark.parametrize("change, said", [
    ({"end_on": "declaration"}, "does not apply to the radbench world.*set end_on source"),
    ({"grid": 25}, "grids of 20 or 30 cells, got grid 25; set grid"),
    ({"walls": 8}, r"walls \(the most obstructions of a radbench episode\) must be 0..7, got 8"),
    ({"sensing": "paper-simple"}, "set sensing realistic"),
    ({"world": "moon"}, "world must be one of grid, radbench"),
])
def test_options_that_do_not_apply_to_the_benchmarks_world_are_refused(change, said):
    with pytest.raises(ValueError, match=said):
        SimCore(SimConfig(**{**RADBENCH, **change}))


# -- the agent's observation and move in the benchmark's world ------------------------------------

IDS = ["agent_0", "agent_1", "agent_2"]
ROOT = Path(__file__).resolve().parents[2]
#: The window-9 team, trained in the benchmark's world (a committed bundle).
WINDOW9 = ROOT / "docs/reproduction/learned-team/main-posterior-cnn9-ft/medc-s0/policy.safetensors"


def _feed(observers, state, episode: int, stamp, map_stamp, geometry) -> None:
    """Hand every observer the poses, readings and status of a core's ``state`` (env.state(0)) as the
    simulator node's messages."""
    for o in observers:
        for j, (cell, value) in enumerate(zip(state.positions, state.readings)):
            o.add_pose(IDS[j], messages.pose_msg(cell, stamp, geometry))
            o.add_reading(IDS[j], messages.reading_msg(IDS[j], value, value, stamp))
        o.add_status(messages.status_msg(IDS, episode, state.step, stamp, map_stamp))


@pytest.mark.parametrize("observation, prior", [
    ("ego9+estimate+posterior", ""), ("maps+estimate", "10,50,16"), ("ego4+estimate", "")])
def test_agent_observation_in_the_benchmarks_world_equals_the_training_worlds(observation, prior):
    """The simulator's benchmark world published as messages gives each agent, bit for bit, the
    observation and move mask the training world (BenchWorld) builds, under the team model's own
    prior and under one given as prior_background (the training world's prior options)."""
    options = dict(agents=3, walls=7, grid=20, max_steps=25, seed=5)
    core = SimCore(SimConfig(**{**RADBENCH, **options}))
    extra = {} if not prior else dict(zip(PRIOR_OPTIONS, background_prior(prior), strict=True))
    ref = make_batched("target_localization", world="radbench", num_envs=1, sensing="realistic",
                       observation=observation, pool=RADBENCH_POOL, **options, **extra)
    ref_obs, ref_mask = ref.reset()
    model = team_model("radbench", "realistic", prior, "greedy")
    assert model == team_sensing(prior or None)
    observers = [TeamObserver(a, 3, 20, observation=observation, sensing=model, world="radbench")
                 for a in IDS]
    assert observers[0].max_walls == OBSTRUCTION_SLOTS
    geometry = GridGeometry(20, 20, 1.0)
    gen = torch.Generator().manual_seed(0)
    sec, episode, map_stamp, steps, obstructions = 0, -1, None, 0, 0
    while len(core.results) < 6:
        sec += 1
        if core.episode != episode:
            episode, map_stamp = core.episode, Time(sec=sec, nanosec=1)
            obstructions += int(core.walls().any())
            for o in observers:
                o.add_map(messages.grid_msg(core.walls(), map_stamp, 1.0))
        _feed(observers, core.env.state(0), core.episode, Time(sec=sec), map_stamp, geometry)
        actions = observe_as_reference(observers, ref_obs, ref_mask, gen)
        result = core.advance(actions)
        out = ref.step(torch.tensor([actions]))
        ref_obs, ref_mask = out.obs, out.mask
        assert (result.finished is not None) == bool(out.done[0])
        steps += 1
    assert steps > 40 and obstructions >= 3


def test_touching_obstructions_are_taken_and_a_map_needing_too_many_rectangles_is_dropped():
    observer = TeamObserver("agent_0", 3, 20, sensing=team_sensing(None), world="radbench")
    touching = torch.zeros(20, 20, dtype=torch.bool)
    touching[2:6, 2:6] = True
    touching[4:9, 5:8] = True  # overlaps the first: an L-shaped union the grid world refuses
    observer.add_map(messages.grid_msg(touching, Time(sec=1), 1.0))
    with pytest.raises(ValueError, match="straight segments one cell thick"):
        grid_world = TeamObserver("agent_0", 3, 20, sensing="realistic")
        grid_world.add_map(messages.grid_msg(touching, Time(sec=1), 1.0))
    checkers = torch.zeros(20, 20, dtype=torch.bool)
    checkers[::2, ::2] = True
    with pytest.raises(ValueError, match=f"take 100 rectangles to cover, more than the {OBSTRUCTION_SLOTS}"):
        observer.add_map(messages.grid_msg(checkers, Time(sec=2), 1.0))


def _bench_set(grid: int, obstructions: int, count: int, seed: int) -> BenchSet:
    episodes, _ = generate_set(grid, 3, obstructions, "medium", count, seed=seed)
    return BenchSet("plain", grid, 1.0, 3, 120, obstructions, "medium", tuple(episodes), "0" * 64)


def _play_with_the_endgame(bench_set: BenchSet, index: int, tau: float, prior: str):
    """Play episode ``index`` of ``bench_set`` to its end in the benchmark's core with the window-9
    team and ``medc-radbench --endgame``'s policy, and alongside in one TeamObserver and Decider per
    agent fed the core's state as messages; check each agent's observation, mask and move. Returns
    (steps, moves the endgame planned in the nodes)."""
    bundle = load_bundle(WINDOW9)
    model = team_model("radbench", "realistic", prior, str(WINDOW9))
    core = BenchCore(bench_set, [index], observation=bundle.observation, sensing=model)
    scores = Endgame(bundle, tau)(core)
    observers = [TeamObserver(a, 3, bench_set.grid, observation=bundle.observation, sensing=model,
                              world="radbench") for a in IDS]
    slot = PolicySlot(tuple(bundle.obs_shape), 8, sensing=model, world="radbench", runtime="torch",
                      observation=bundle.observation)
    slot.swap(str(WINDOW9))
    deciders = [Decider(slot, o, None, True, logging.getLogger("plain"), tau) for o in observers]
    geometry = GridGeometry(bench_set.grid, bench_set.grid, 1.0)
    obs, mask = core.reset()
    map_stamp = Time(sec=1, nanosec=1)
    for o in observers:
        o.add_map(messages.grid_msg(core.state(0).walls, map_stamp, 1.0))
    for step in range(bench_set.max_steps):
        _feed(observers, core.state(0), 0, Time(sec=2 + step), map_stamp, geometry)
        with torch.no_grad():
            logits = scores(obs.reshape(3, *core.obs_shape), mask.reshape(3, 8))
        expected = masked_logits(logits, mask.reshape(3, 8)).argmax(-1).tolist()
        moves = []
        for i, (o, d) in enumerate(zip(observers, deciders)):
            own_obs, own_mask, tick = o.observe()
            assert torch.equal(own_obs, obs[0, i]) and torch.equal(own_mask, mask[0, i])
            moves.append(d.decide(own_obs, own_mask, tick))
        assert moves == expected, f"step {step}"
        out = core.step(torch.tensor([moves]))
        obs, mask = out.obs, out.mask
        if bool(out.done[0]):
            return step + 1, sum(d.planned for d in deciders)
    raise AssertionError("the episode did not end within max_steps")


@pytest.mark.parametrize("grid, prior", [(20, "10,50,16"), (30, "")])
def test_the_agents_moves_with_the_endgame_are_medc_radbench_endgames(grid, prior):
    """The window-9 team with the classical endgame at tau 0.9, as agent nodes decide (observation
    from messages, the endgame's shortest-path move or the bundle's), makes exactly the moves
    medc-radbench --endgame 0.9 makes in the benchmark's core, step by step; the endgame plans some
    and the bundle decides others."""
    bench_set = _bench_set(grid, 5, 3, seed=41)
    steps = planned = 0
    for index in range(3):
        s, p = _play_with_the_endgame(bench_set, index, 0.9, prior)
        steps, planned = steps + s, planned + p
    assert 0 < planned < 3 * steps


def test_the_endgame_moves_along_a_shortest_path_and_stays_off_at_tau_one():
    """Once the posterior's mode holds tau, an agent that can reach its success region moves one step
    closer along free cells; tau 1.0 never plans."""
    from medc_training.radbench.oracle import success_field

    bench_set = _bench_set(20, 3, 1, seed=43)
    _, planned = _play_with_the_endgame(bench_set, 0, 0.6, "")
    assert planned > 0
    observer = TeamObserver("agent_0", 3, 20, sensing=team_sensing(None), world="radbench")
    observer.add_map(messages.grid_msg(torch.zeros(20, 20, dtype=torch.bool), Time(sec=1, nanosec=1), 1.0))
    state = SimpleNamespace(positions=((0, 0), (19, 19), (0, 19)), readings=(2000.0, 10.0, 10.0), step=0)
    _feed([observer], state, 0, Time(sec=2), Time(sec=1, nanosec=1), GridGeometry(20, 20, 1.0))
    _, mask, _ = observer.observe()
    posterior = observer.memory.posterior()
    tau = min(float(posterior.max()), 0.99)
    assert endgame_move(observer, 1.0, mask) is None
    move = endgame_move(observer, tau, mask)
    mode = int(posterior.argmax())
    field = success_field(observer.walls, torch.tensor([[mode // 20, mode % 20]]), observer.sensing)[0]
    assert move is not None and field[0, 0] > 0  # agent_0 at (0, 0) is outside the mode's success region
    row, col = ACTIONS[move]
    assert field[row, col] == field[0, 0] - 1  # one move nearer it
    nearer = [a for a, (r, c) in enumerate(ACTIONS) if bool(mask[a]) and field[r, c] == field[0, 0] - 1]
    assert move == nearer[0]  # the first of the moves that bring it nearer, as the evaluator's argmax


def test_in_the_benchmarks_world_the_agent_takes_its_bundles_under_the_team_model_and_their_prior(tmp_path):
    """World radbench: a benchmark bundle runs without allow_other_world, under the team model with
    the prior its manifest records (or the one given, which must agree with it); the grid world still
    refuses it, and a bundle whose recorded prior differs from the team's is refused."""
    from conftest import make_bundle
    from medc_agents.bench_team import check_endgame_tau
    from medc_agents.policy_slot import PolicyRejected

    wide = {"world": "radbench", "prior_background_low": 5.0, "prior_background_high": 100.0,
            "prior_background_levels": 16}
    widened = make_bundle(tmp_path / "wide.safetensors", 7, grid=20, sensing="realistic", environment=wide)
    plain = make_bundle(tmp_path / "plain.safetensors", 8, grid=20, sensing="realistic",
                        environment={"world": "radbench"})
    own = team_model("radbench", "realistic", "", str(widened))
    assert (own.background, own.levels[1]) == ((5.0, 100.0), 16) and own.name == "realistic"
    assert team_model("radbench", "realistic", "", str(plain)) == team_sensing(None)
    PolicySlot((5, 20, 20), 8, sensing=own, world="radbench", grid=20).swap(str(widened))
    PolicySlot((5, 20, 20), 8, sensing=team_model("radbench", "realistic", "5,100,16", "greedy"),
               world="radbench", grid=20).swap(str(widened))
    with pytest.raises(PolicyRejected, match="background prior 5-100 counts/s at 16 levels, but this team's "
                                             "model weighs 10-50 at 16"):
        narrow = PolicySlot((5, 20, 20), 8, sensing=team_sensing("10,50,16"), world="radbench", grid=20)
        narrow.swap(str(widened))
    with pytest.raises(PolicyRejected, match="trained in the 'radbench' world, but it is about to run in the "
                                             "'grid' world"):
        PolicySlot((5, 20, 20), 8, sensing="realistic", grid=20).swap(str(plain))
    slot = PolicySlot(tuple(load_bundle(WINDOW9).obs_shape), 8, sensing=team_sensing("10,50,16"),
                      world="radbench", grid=20)
    slot.swap(str(WINDOW9))  # records no prior: runs under any the team weighs
    for args, said in [(("grid", "realistic", "10,50,16", "greedy"), "applies with world radbench only"),
                       (("radbench", "paper-simple", "", "greedy"), "set sensing realistic"),
                       (("radbench", "realistic", "10,50", "greedy"), "prior_background: .*LOW,HIGH,LEVELS"),
                       (("moon", "realistic", "", "greedy"), "world must be one of grid, radbench")]:
        with pytest.raises(ValueError, match=said):
            team_model(*args)
    assert team_model("grid", "realistic", "", str(plain)) == "realistic"
    for tau in (0.0, 1.5, True, "0.9"):
        with pytest.raises(ValueError, match=r"endgame_tau must be a number in \(0, 1\]"):
            check_endgame_tau(tau)
    assert check_endgame_tau(1) == 1.0


def test_the_launcher_takes_the_world_from_the_bundle_and_passes_the_prior_and_endgame(tmp_path):
    """medc-launch with world null runs a benchmark bundle's world (and its scenario) in the simulator
    and every agent, passes prior_background and endgame_tau to the agents, and refuses, before any
    node starts, a bundle of one world in a graph of the other, saying what to set."""
    from conftest import make_bundle
    from medc_bringup.launcher import agent_parameters, load_config, resolve_policies, sim_parameters

    cfg = load_config(None, policy=str(WINDOW9), prior_background="10,50,16", endgame_tau=0.9)
    assert resolve_policies(cfg) == [str(WINDOW9)] * 3
    sim = sim_parameters(cfg, episodes=2)
    assert (sim["world"], sim["grid"], sim["walls"], sim["max_steps"], sim["sensing"]) == (
        "radbench", 20, 7, 120, "realistic")
    agent = agent_parameters(cfg, 1, str(WINDOW9))
    assert (agent["world"], agent["prior_background"], agent["endgame_tau"]) == ("radbench", "10,50,16", 0.9)
    default = load_config(None)
    resolve_policies(default)  # the default team: classical controllers, in the grid world
    assert default.world == "grid" and agent_parameters(default, 0, "infotaxis")["endgame_tau"] == 1.0
    with pytest.raises(ValueError, match=r"trained in the 'radbench' world.*set world: radbench"):
        resolve_policies(load_config(None, policy=str(WINDOW9), world="grid"))
    gridded = make_bundle(tmp_path / "grid.safetensors", 10, grid=20, sensing="realistic")
    with pytest.raises(ValueError, match=r"trained in the 'grid' world.*set world: grid"):
        resolve_policies(load_config(None, policy=str(gridded), world="radbench"))
    wide = make_bundle(tmp_path / "wide.safetensors", 9, grid=20, sensing="realistic", environment={
        "world": "radbench", "prior_background_low": 5.0, "prior_background_high": 100.0,
        "prior_background_levels": 16})
    resolve_policies(load_config(None, policy=str(wide)))  # under its own prior
    with pytest.raises(ValueError, match=r"background prior 5-100.*prior_background"):
        resolve_policies(load_config(None, policy=str(wide), prior_background="10,50,16"))
    with pytest.raises(ValueError, match="set end_on source"):
        resolve_policies(load_config(None, policy=str(WINDOW9), end_on="declaration"))
    with pytest.raises(ValueError, match="applies with world radbench only"):
        resolve_policies(load_config(None, prior_background="10,50,16"))
    for key, value, said in [("world", "moon", "world in .* must be one of grid, radbench"),
                             ("prior_background", "10,50", "prior_background in .*LOW,HIGH,LEVELS"),
                             ("endgame_tau", 1.5, r"endgame_tau must be a number in \(0, 1\]")]:
        with pytest.raises(ValueError, match=said):
            load_config(None, **{key: value})
