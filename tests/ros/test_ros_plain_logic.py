"""The ROS nodes' logic on hand-built messages, without spinning a node."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from builtin_interfaces.msg import Time
from conftest import make_bundle
from medc_agents.policy_slot import PolicyRejected, PolicySlot, looks_like_cid
from medc_agents.team_state import TeamObserver
from medc_bringup.launcher import agent_parameters, load_config, resolve_policies, ros_args, sim_parameters
from medc_common.contract import GridGeometry, agent_index, xy_to_cell
from medc_sim import messages
from medc_sim.moves import MoveBook, MoveRejected
from medc_sim.sim_core import SimConfig, SimCore
from medc_training.envs import make_batched
from medc_training.envs.grid import ACTIONS
from ros_helpers import feed_step, observe_as_reference

IDS = ["agent_0", "agent_1", "agent_2"]
GEO10 = GridGeometry(10, 10, 1.0)


@pytest.mark.parametrize(("noise", "observation"),
                         [(False, "maps"), (True, "maps"), (True, "maps+estimate"), (False, "ego4+estimate"),
                          (True, "ego9+estimate"), (True, "ego3"), (True, "maps+posterior"),
                          (True, "ego6+estimate+posterior")])
def test_agent_observation_from_messages_equals_training_observation(noise, observation):
    """Messages -> TeamObserver gives bit-identical observations and masks to the env, every step,
    for every observation variant."""
    steps = _play_observation_parity(noise, observation, walls=1)
    assert steps > 30


@pytest.mark.parametrize("observation", ["maps", "maps+estimate", "ego4+estimate", "ego9+estimate",
                                         "ego6+estimate+posterior"])
def test_agent_observation_equals_training_observation_under_realistic_sensing(observation):
    """The same, under the realistic sensing preset: Poisson counts of an unknown strength and
    background, walls that block the line of sight (two wall segments), success within 1.1 cells;
    the simulator ends the episodes where the core does, and some end beside the source."""
    steps, beside = _play_observation_parity(None, observation, walls=2, sensing="realistic")
    assert steps > 30 and beside > 0


def _play_observation_parity(noise, observation, walls, sensing=None):
    """Play 6 episodes with random valid moves in a SimCore and in the env, feeding the sim's messages
    to one TeamObserver per agent; check every observation and mask, and every episode's end.
    Returns the steps played (and, with ``sensing``, how many episodes ended with no agent on the
    source cell)."""
    extra = {} if sensing is None else {"sensing": sensing}
    core = SimCore(SimConfig(agents=3, walls=walls, grid=10, max_steps=15, seed=5, noise=bool(noise),
                             **extra))
    ref = make_batched(
        "target_localization", num_envs=1, seed=5, agents=3, walls=walls, grid=10, max_steps=15, noise=noise,
        observation=observation, **extra,
    )
    ref_obs, ref_mask = ref.reset()
    observers = [TeamObserver(a, 3, 10, observation=observation, **extra) for a in IDS]
    gen = torch.Generator().manual_seed(0)
    sec, episode, map_stamp, steps, beside = 0, -1, None, 0, 0
    while len(core.results) < 6:
        sec += 1
        if core.episode != episode:
            episode, map_stamp = core.episode, Time(sec=sec, nanosec=1)
            for o in observers:
                o.add_map(messages.grid_msg(core.walls(), map_stamp, 1.0))
        feed_step(observers, core, Time(sec=sec), map_stamp, IDS, GEO10)
        actions = observe_as_reference(observers, ref_obs, ref_mask, gen)
        target = core.target()
        # Every move is valid (masked), so this is where the agents stand after it.
        moved = [(r + ACTIONS[a][0], c + ACTIONS[a][1]) for (r, c), a in zip(core.positions(), actions)]
        result = core.advance(actions)
        out = ref.step(torch.tensor([actions]))
        ref_obs, ref_mask = out.obs, out.mask
        assert (result.finished is not None) == bool(out.done[0])
        if result.finished is not None:
            assert result.finished.success == bool(out.success[0])
            beside += result.finished.success and target not in moved
        steps += 1
    if sensing is None:
        return steps
    return steps, beside


def test_missing_move_means_stay():
    core = SimCore(SimConfig(agents=3, walls=0, grid=10, max_steps=50, seed=1))
    before = core.positions()
    core.advance([None, None, None])
    assert core.positions() == before
    moves = [int(core.env.state(0).mask[i].nonzero()[0]) for i in range(3)]
    core.advance([moves[0], None, None])
    after = core.positions()
    assert after[0] != before[0] and after[1:] == before[1:]


def test_move_book_drops_bad_moves():
    book = MoveBook(3, 8)
    book.open(2, 5)
    with pytest.raises(MoveRejected, match="unknown agent"):
        book.offer("agent_7", 2, 5, 1)
    with pytest.raises(MoveRejected, match="episode 1 step 5"):
        book.offer("agent_0", 1, 5, 1)  # an episode that has ended
    with pytest.raises(MoveRejected, match=r"not in 0\.\.7"):
        book.offer("agent_0", 2, 5, 8)
    assert not book.complete and book.missing == [0, 1, 2]
    for i in range(3):
        book.offer(IDS[i], 2, 5, i)
    assert book.complete and book.actions() == [0, 1, 2]
    book.open(2, 6)
    assert book.offer("agent_1", 2, 5, 1) is None  # a late re-send of its move for step 5: ignored
    with pytest.raises(MoveRejected):
        book.offer("agent_1", 2, 4, 3)  # older than that: dropped and logged
    assert book.missing == [0, 1, 2]


def test_observer_rejects_bad_messages():
    o = TeamObserver("agent_1", 3, 10)
    stamp = Time(sec=1)
    walls = torch.zeros((10, 10), dtype=torch.bool)
    o.add_map(messages.grid_msg(walls, Time(sec=0, nanosec=5), 1.0))  # the grid geometry for poses
    bad_map = messages.grid_msg(walls, stamp, 1.0)
    bad_map.data = bad_map.data[:-1]
    with pytest.raises(ValueError, match="99 cells"):
        o.add_map(bad_map)
    with pytest.raises(ValueError, match="8x8"):
        o.add_map(messages.grid_msg(torch.zeros((8, 8), dtype=torch.bool), stamp, 1.0))
    pose = messages.pose_msg((2, 3), stamp, GEO10)
    pose.pose.position.x = math.nan
    with pytest.raises(ValueError, match="not finite"):
        o.add_pose("agent_0", pose)
    # Off every map held while its step is not known yet: held unchecked (its area's map may be on
    # its way) and checked once a status names the map; the good pose below replaces it.
    o.add_pose("agent_0", messages.pose_msg((12, 3), stamp, GEO10))
    with pytest.raises(ValueError, match="unknown agent"):
        o.add_pose("agent_3", messages.pose_msg((2, 3), stamp, GEO10))
    with pytest.raises(ValueError, match="names agent"):
        o.add_reading("agent_0", messages.reading_msg("agent_2", 1.0, 0.0, stamp))
    with pytest.raises(ValueError, match="finite"):
        o.add_reading("agent_0", messages.reading_msg("agent_0", math.nan, 0.0, stamp))
    with pytest.raises(ValueError, match="agents"):
        o.add_status(messages.status_msg(["agent_0", "agent_1"], 0, 0, stamp, stamp))
    # Nothing bad was kept: a complete good step still gives an observation.
    o.add_map(messages.grid_msg(walls, stamp, 1.0))
    for j in range(3):
        o.add_pose(IDS[j], messages.pose_msg((j, j), stamp, GEO10))
        o.add_reading(IDS[j], messages.reading_msg(IDS[j], 2.0, 0.0, stamp))
    o.add_status(messages.status_msg(IDS, 0, 0, stamp, stamp))
    obs, mask, tick = o.observe()
    assert obs.shape == (5, 10, 10) and obs[0, 1, 1] == 1 and obs[1, 0, 0] == 1 and obs[1, 2, 2] == 1
    assert (tick.episode, tick.step) == (0, 0) and mask.shape == (8,)


def test_policy_slot_refuses_bad_bundles_and_keeps_the_old_one(bundles, tmp_path):
    slot = PolicySlot((5, 10, 10), 8)
    slot.swap(str(bundles["a"]))
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x00" * 64)
    for source, reason in [
        ("", "empty"),
        (str(tmp_path / "missing.safetensors"), "not an existing file"),
        (str(tmp_path), "not an existing file"),
        ("bad\x00path", "NUL"),
        (str(garbage), "invalid"),
        (str(bundles["grid30"]), "shape"),
        ("QmYwAPJzv5CZsnA625s3Xf2nemtYgPpHdWEz79ojWnPbdG", "content id"),
    ]:
        with pytest.raises(PolicyRejected, match=reason):
            slot.swap(source)
        assert slot.current.source == str(bundles["a"])
    assert looks_like_cid("ipfs://QmYwAPJzv5CZsnA625s3Xf2nemtYgPpHdWEz79ojWnPbdG")
    north = PolicySlot((5, 10, 10), 8)
    north.swap(str(bundles["north"]))
    assert north.act(torch.zeros(5, 10, 10), torch.ones(8, dtype=torch.bool)) == 0
    assert north.act(torch.zeros(5, 10, 10), torch.tensor([False] + [True] * 7)) != 0


def test_policy_slot_runs_the_network_in_its_runtime_and_says_which(bundles, monkeypatch, tmp_path):
    """The default 'auto' runs a bundle in onnxruntime (the same moves as PyTorch); 'torch' in
    PyTorch; 'onnxruntime' where it is missing refuses the bundle and keeps the running one; a
    controller runs in neither."""
    obs = torch.rand((5, 10, 10), generator=torch.Generator().manual_seed(0))
    mask = torch.ones(8, dtype=torch.bool)
    auto, plain = PolicySlot((5, 10, 10), 8), PolicySlot((5, 10, 10), 8, runtime="torch")
    for slot in (auto, plain):
        slot.swap(str(bundles["a"]))
    assert auto.runs_in() == ", network in onnxruntime" and plain.runs_in() == ", network in torch"
    assert auto.act(obs, mask) == plain.act(obs, mask) == int(auto.current.bundle.act(obs[None])[0])
    strict = PolicySlot((5, 10, 10), 8, runtime="onnxruntime")
    strict.swap(str(bundles["north"]))
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    fresh = make_bundle(tmp_path / "fresh.safetensors", 7)  # loaded in no runtime yet
    with pytest.raises(PolicyRejected, match="onnxruntime is not installed"):
        strict.swap(str(fresh))
    assert strict.current.source == str(bundles["north"]) and strict.decider.runtime == "onnxruntime"
    fallback = PolicySlot((5, 10, 10), 8)
    fallback.swap(str(fresh))
    assert fallback.runs_in().startswith(", network in torch (onnxruntime is not installed")
    fallback.swap("greedy")
    assert fallback.decider is None and fallback.runs_in() == ""
    with pytest.raises(ValueError, match="runtime must be one of"):
        PolicySlot((5, 10, 10), 8, runtime="tensorrt")


def test_policy_slot_follows_or_enforces_the_bundle_observation(bundles, tmp_path):
    from medc_training.bundle import save_bundle
    from medc_training.envs.tl_observation import observation_shape, parse_observation
    from medc_training.nets import make_actor_critic

    def named_bundle(name: str):
        net = make_actor_critic("mlp", observation_shape(parse_observation(name), 10), 8)
        return save_bundle(tmp_path / f"{name}.safetensors", net, {"application": "target_localization",
                           "observation": {"name": name}, "environment": {"grid": 10}})

    ego = named_bundle("ego4+estimate")
    follow = PolicySlot((5, 10, 10), 8, grid=10)  # observation None: the bundle's own
    follow.swap(str(bundles["a"]))
    assert (follow.observation, follow.obs_shape) == ("maps", (5, 10, 10))
    follow.swap(str(ego))
    assert (follow.observation, follow.obs_shape) == ("ego4+estimate", (5, 9, 9))
    assert follow.act(torch.zeros(5, 9, 9), torch.ones(8, dtype=torch.bool)) in range(8)
    fixed = PolicySlot((5, 10, 10), 8, observation="maps")
    fixed.swap(str(bundles["a"]))
    with pytest.raises(PolicyRejected,
                       match="takes the observation 'ego4\\+estimate', but this environment produces 'maps'"):
        fixed.swap(str(ego))
    assert fixed.current.source == str(bundles["a"])
    # A bundle that takes the posterior as well: followed, and refused where the estimate alone is made.
    both = named_bundle("ego4+estimate+posterior")
    follow.swap(str(both))
    assert (follow.observation, follow.obs_shape) == ("ego4+estimate+posterior", (6, 9, 9))
    estimate_only = PolicySlot((5, 9, 9), 8, observation="ego4+estimate")
    estimate_only.swap(str(ego))
    with pytest.raises(PolicyRejected, match="takes the observation 'ego4\\+estimate\\+posterior', but this "
                                             "environment produces 'ego4\\+estimate'"):
        estimate_only.swap(str(both))
    assert estimate_only.current.source == str(ego)


def test_bundle_for_one_sensing_preset_is_refused_under_the_other(bundles, tmp_path):
    """A bundle records the sensing preset it was trained under (environment.sensing; none means
    paper-simple): the policy slot and the launcher refuse it for a team that senses with the other
    preset, naming both, and take it under its own."""
    from medc_training.bundle import BundleError, check_sensing, manifest_sensing, read_manifest

    realistic, simple = bundles["realistic"], bundles["a"]
    assert manifest_sensing(read_manifest(realistic)) == "realistic"
    assert manifest_sensing(read_manifest(simple)) == "paper-simple"  # a manifest without it
    both = "trained under the sensing model 'realistic', but this team senses with 'paper-simple'"
    slot = PolicySlot((5, 10, 10), 8)  # the default team: paper-simple
    slot.swap(str(simple))
    with pytest.raises(PolicyRejected, match=both):
        slot.swap(str(realistic))
    assert slot.current.source == str(simple)  # the old one keeps running
    team = PolicySlot((5, 10, 10), 8, sensing="realistic")
    team.swap(str(realistic))
    with pytest.raises(PolicyRejected, match="'paper-simple', but this team senses with 'realistic'"):
        team.swap(str(simple))
    assert team.current.source == str(realistic)
    follow = PolicySlot((5, 10, 10), 8, grid=10, sensing="realistic")  # the bundle's observation
    follow.swap(str(realistic))
    # A bundle whose estimator was trained under a wider background prior than the preset's.
    wider = make_bundle(tmp_path / "wider.safetensors", 5, sensing="realistic", environment={
        "prior_background_low": 5.0, "prior_background_high": 100.0, "prior_background_levels": 16})
    with pytest.raises(PolicyRejected, match="background prior 5-100 counts/s at 16 levels, but this "
                                             "team's model weighs 10-50 at 16"):
        team.swap(str(wider))
    assert team.current.source == str(realistic)
    # The launcher: a preset given in the config must be every bundle's; null takes the bundle's.
    with pytest.raises(ValueError, match=both):
        resolve_policies(load_config(None, policy=str(realistic), sensing="paper-simple"))
    with pytest.raises(ValueError, match="'paper-simple', but this team senses with 'realistic'"):
        resolve_policies(load_config(None, policy=str(simple), sensing="realistic"))
    cfg = load_config(None, policy=str(realistic))
    assert resolve_policies(cfg) == [str(realistic)] * 3 and cfg.sensing == "realistic"
    cfg = load_config(None, policy=str(simple))
    assert resolve_policies(cfg) == [str(simple)] * 3 and cfg.sensing == "paper-simple"
    with pytest.raises(ValueError, match="'realistic', but this team senses with 'paper-simple'"):
        resolve_policies(load_config(None, policy=str(simple), policies={"agent_1": str(realistic)}))
    with pytest.raises(ValueError, match=r"sensing .* must be one of"):
        load_config(None, sensing="noisy")
    # Both nodes are given the launcher's preset.
    cfg = load_config(None, policy=str(realistic))
    resolve_policies(cfg)
    assert sim_parameters(cfg)["sensing"] == "realistic"
    assert agent_parameters(cfg, 0, str(realistic))["sensing"] == "realistic"
    with pytest.raises(BundleError, match=r"environment\.sensing is 'noisy'"):
        check_sensing({"environment": {"sensing": "noisy"}}, "paper-simple")


def test_bundle_from_another_world_is_refused_unless_allowed(bundles, tmp_path):
    """A bundle trained in the benchmark's world with domain randomisation (its manifest's
    environment.world and options) is refused by the policy slot and the launcher, the message naming
    the world and the options, and taken under allow_other_world, which every agent is given (here in
    the grid world, set in the config: world null would take the bundle's)."""
    grid, other = bundles["a"], bundles["radbench"]
    said = "trained in the 'radbench' world with transmission_max=0.3, walls_min=2, but it is about to run"
    slot = PolicySlot((5, 10, 10), 8)
    slot.swap(str(grid))
    with pytest.raises(PolicyRejected, match=said):
        slot.swap(str(other))
    assert slot.current.source == str(grid)  # the old one keeps running
    allowed = PolicySlot((5, 10, 10), 8, grid=10, allow_other_world=True)
    allowed.swap(str(other))
    assert allowed.current.source == str(other)
    # The launcher: refused before any node starts unless the config allows it.
    with pytest.raises(ValueError, match=f"{said}.*launch config key allow_other_world"):
        resolve_policies(load_config(None, policy=str(other)))
    with pytest.raises(ValueError, match=said):
        resolve_policies(load_config(None, policy=str(grid), policies={"agent_2": str(other)}))
    config = tmp_path / "launch.yaml"
    config.write_text(f"policy: {other}\nallow_other_world: true\nworld: grid\n")
    cfg = load_config(config)
    assert resolve_policies(cfg) == [str(other)] * 3
    assert agent_parameters(cfg, 0, str(other))["allow_other_world"] is True
    assert agent_parameters(load_config(None, policy=str(grid)), 0, str(grid))["allow_other_world"] is False
    with pytest.raises(ValueError, match=r"allow_other_world .* must be bool"):
        load_config(None, allow_other_world="yes")


def test_realistic_observer_takes_only_maps_of_wall_segments():
    """Under the realistic preset a map's walls must be segments the exact line of sight takes as one
    rectangle each, at most as many as the environment places on the grid; the paper-simple rule
    samples the line and takes any map."""
    from medc_agents.team_messages import check_wall_segments

    stamp = Time(sec=1)
    straight = torch.zeros(10, 10, dtype=torch.bool)
    straight[2, 1:5] = True
    straight[5:9, 7] = True
    ell = straight.clone()
    ell[3:6, 1] = True  # an L: the first segment turns down
    crowd = torch.zeros(10, 10, dtype=torch.bool)
    crowd[0:9:2, 0] = crowd[0:9:2, 9] = True  # 10 single-cell segments
    realistic = TeamObserver("agent_0", 3, 10, sensing="realistic")
    assert realistic.max_walls == 2
    realistic.add_map(_map(straight, stamp))
    with pytest.raises(ValueError, match="straight segments one cell thick"):
        realistic.add_map(_map(ell, stamp))
    with pytest.raises(ValueError, match="10 wall segments; this agent's grid takes at most 2"):
        realistic.add_map(_map(crowd, stamp))
    with pytest.raises(ValueError, match="unknown sensing preset"):
        TeamObserver("agent_0", 3, 10, sensing="noisy")
    simple = TeamObserver("agent_0", 3, 10)
    for walls in (straight, ell, crowd):
        simple.add_map(_map(walls, stamp))
    check_wall_segments(straight, 2)


def test_contract_conversions():
    assert agent_index("agent_2", 3) == 2
    with pytest.raises(ValueError):
        agent_index("agent_3", 3)
    with pytest.raises(ValueError):
        agent_index("robot", 3)
    # REP 103: y north; environment row 0 is the northern row, at the top of the grid.
    assert xy_to_cell(3.5, 2.5, 1.0, 10, 10) == (7, 3)
    assert xy_to_cell(350.0, 950.0, 100.0, 10, 10) == (0, 3)


def test_launch_config_is_checked(tmp_path, bundles):
    with pytest.raises(ValueError, match="unknown key"):
        bad = tmp_path / "bad.yaml"
        bad.write_text("agent: 3\n")
        load_config(bad)
    with pytest.raises(ValueError, match="mode"):
        load_config(None, mode="fast")
    cfg = load_config(None, policy=str(bundles["a"]), agents=2)
    assert resolve_policies(cfg) == [str(bundles["a"])] * 2
    assert (cfg.grid, cfg.max_steps) == (10, 100)  # grid from the bundle's manifest, max_steps default
    with pytest.raises(ValueError, match="does not exist"):
        resolve_policies(load_config(None, policy=str(tmp_path / "none")))
    with pytest.raises(ValueError, match="shape"):
        resolve_policies(load_config(None, policy=str(bundles["a"]), grid=30))
    team = tmp_path / "team"
    team.mkdir()
    for name in ("a", "north"):
        (team / f"team_agent_{1 if name == 'north' else 0}.safetensors").write_bytes(
            bundles[name].read_bytes()
        )
    paths = resolve_policies(load_config(None, policy=str(team), agents=3))
    assert [Path(p).name for p in paths] == [
        "team_agent_0.safetensors",
        "team_agent_1.safetensors",
        "team_agent_0.safetensors",
    ]
    args = ros_args("medc_sim", {"seed": 3, "noise": False, "namespace": "/medc"})
    assert args == [
        "--ros-args",
        "-r",
        "__node:=medc_sim",
        "-p",
        "seed:=3",
        "-p",
        "noise:=false",
        "-p",
        'namespace:="/medc"',
    ]


def test_console_script_works_without_sourcing_env_sh():
    """A node started from a plain shell finds medc_interfaces (re-executed with the ROS paths)."""
    plain_shell = ("LD_LIBRARY_PATH", "PYTHONPATH", "AMENT_PREFIX_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")
    env = {k: v for k, v in os.environ.items() if k not in plain_shell}
    code = (
        "from medc_common.ros_env import ensure_interfaces; ensure_interfaces(); "
        "import rclpy; from medc_interfaces.msg import RadiationReading; "
        "rclpy.init(); n = rclpy.create_node('probe'); n.create_publisher(RadiationReading, 'r', 1); "
        "print('ok'); n.destroy_node(); rclpy.shutdown()"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_console_script_without_a_built_interface_package_says_what_to_do(tmp_path):
    plain_shell = ("LD_LIBRARY_PATH", "PYTHONPATH", "AMENT_PREFIX_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")
    env = {k: v for k, v in os.environ.items() if k not in plain_shell}
    env["MEDC_ROOT"] = str(tmp_path)  # a checkout where scripts/build_interfaces.sh never ran
    script = Path(sys.executable).parent / "medc-sim"
    out = subprocess.run([str(script)], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "bash scripts/setup.sh" in out.stderr and "Traceback" not in out.stderr


def test_bridge_connects_only_to_loopback_endpoints(tmp_path):
    from medc_registry.bridge_node import BridgeError, RegistryBridge, connect_registry

    with pytest.raises(BridgeError, match="loopback"):
        connect_registry("http://10.0.0.5:8545", str(tmp_path))
    with pytest.raises(BridgeError, match="loopback"):
        connect_registry("embedded", "http://ipfs.example.com:5001")
    with pytest.raises(BridgeError, match="contract addresses"):
        connect_registry("http://127.0.0.1:8545", str(tmp_path))
    bridge = RegistryBridge(registry=None, cache_dir=tmp_path / "cache")
    with pytest.raises(BridgeError, match="JSON object"):
        bridge.request("target_localization", "[1, 2]")
    with pytest.raises(BridgeError, match="required"):
        bridge.request("target_localization", "")
    with pytest.raises(BridgeError, match=r"\[0, 1\]"):
        bridge.review(0, "Qm", 1.5)
    with pytest.raises(BridgeError, match="no allocation"):
        bridge.review(0, "QmUnknown", 0.5)
    with pytest.raises(BridgeError, match="not a content id"):
        bridge.fetch("../secrets")


def test_map_frame_follows_rep_103():
    """One mapping (medc_common.contract): x east, y north; message row j = environment row H-1-j;
    move N (row - 1) heads +y, E (col + 1) heads +x; the OccupancyGrid origin is honoured."""
    import math as m

    from medc_common import contract
    from medc_training.envs.grid import ACTIONS

    g = GridGeometry(10, 10, 1.0)
    assert len(contract.MOVE_STEPS) == len(contract.MOVE_HEADINGS) == len(ACTIONS)
    assert g.cell_to_xy(0, 0) == (0.5, 9.5)  # environment row 0 = the northern row
    assert g.cell_to_xy(9, 3) == (3.5, 0.5)
    for action, (drow, dcol) in enumerate(ACTIONS):
        di, dj = contract.MOVE_STEPS[action]
        assert (di, dj) == (dcol, -drow)
        x0, y0 = g.cell_to_xy(5, 5)
        x1, y1 = g.cell_to_xy(5 + drow, 5 + dcol)
        assert m.isclose(m.atan2(y1 - y0, x1 - x0), contract.MOVE_HEADINGS[action])
    assert contract.MOVE_HEADINGS[0] == m.pi / 2 and contract.MOVE_HEADINGS[2] == 0.0  # N, E
    # Any point of a cell's square snaps to it (altitude and yaw are not looked at).
    assert g.xy_to_cell(3.01, 0.99) == g.xy_to_cell(3.99, 0.0) == (9, 3)
    # A translated, rotated origin (yaw pi/2: the grid's +x points north).
    r = GridGeometry(10, 10, 2.0, origin_x=-5.0, origin_y=3.0, origin_yaw=m.pi / 2)
    x, y = r.cell_to_xy(9, 0)  # message cell (0, 0): centre (1, 1) m from the origin, rotated
    assert m.isclose(x, -6.0) and m.isclose(y, 4.0)
    for row, col in [(0, 0), (3, 7), (9, 9)]:
        assert r.xy_to_cell(*r.cell_to_xy(row, col)) == (row, col)
    assert m.isclose(r.move_heading(2), m.pi / 2)  # E of the grid = north in the map frame
    # Walls: message data row 0 is the southern row.
    walls = torch.zeros((4, 3), dtype=torch.bool)
    walls[0, 2] = True  # north-east corner
    data = contract.walls_to_occupancy(walls)
    assert data[3 * 3 + 2] == 100 and sum(data) == 100
    assert (contract.occupancy_to_walls(data, 4, 3) == walls.numpy()).all()


def test_agent_takes_its_action_count_from_the_environment():
    """The agent node checks bundles against the environment's action count, not a literal."""
    from medc_agents.node import NUM_ACTIONS

    assert make_batched("target_localization", grid=10, walls=1).num_actions == NUM_ACTIONS


def _map(walls, load: Time, header: Time | None = None, resolution: float = 1.0, origin=(0.0, 0.0)):
    msg = messages.grid_msg(walls, load, resolution)
    msg.header.stamp = header or load
    msg.info.origin.position.x, msg.info.origin.position.y = origin
    return msg


def _round(o: TeamObserver, cells, stamp: Time, episode: int, step: int, map_stamp: Time, geo=GEO10):
    for j, cell in enumerate(cells):
        o.add_pose(IDS[j], messages.pose_msg(cell, stamp, geo))
        o.add_reading(IDS[j], messages.reading_msg(IDS[j], 5.0 + j, 0.0, stamp))
    return o.add_status(messages.status_msg(IDS, episode, step, stamp, map_stamp))


def test_observer_follows_a_restarted_driver_and_says_what_a_step_waits_for():
    walls = torch.zeros((10, 10), dtype=torch.bool)
    o = TeamObserver("agent_0", 3, 10)
    m1 = Time(sec=100)
    o.add_map(_map(walls, m1))
    cells = [(1, 1), (2, 2), (3, 3)]
    for step in range(3):
        _round(o, cells, Time(sec=101 + step), 4, step, m1)
        assert o.ready()
        o.observe()
    # A re-sent step (same stamp) is answered already; an older step of the same episode is dropped.
    assert o.answered_tick(_round(o, cells, Time(sec=103), 4, 2, m1))
    with pytest.raises(ValueError, match="older than the one answered"):
        _round(o, cells, Time(sec=104), 4, 1, m1)
    # The driver restarts: episode 0 step 0 on a new map (even with the same map, step 0 restarts).
    m2 = Time(sec=200)
    o.add_map(_map(walls, m2))
    _round(o, [(5, 5), (6, 6), (7, 7)], Time(sec=201), 0, 0, m2)
    assert o.ready()
    _, _, tick = o.observe()
    assert (tick.episode, tick.step) == (0, 0) and "the driver restarted" in o.notes[-1]
    assert float(o.memory.visit_map.sum()) == 3  # memory reset: only this step's visits
    _round(o, cells, Time(sec=202), 0, 0, m2)  # step 0 again with a new stamp: a new start
    assert o.ready()

    # A map_stamp equal to the map's header.stamp while its map_load_time is 0: said precisely.
    o2 = TeamObserver("agent_0", 3, 10)
    o2.add_map(_map(walls, Time(sec=0), header=Time(sec=7)))
    _round(o2, cells, Time(sec=8), 0, 0, Time(sec=7))
    need, have = o2.waiting_for()
    assert not o2.ready() and "info.map_load_time 7.000000000" in need[0]
    assert any("header.stamp is 7.000000000 has info.map_load_time 0.000000000" in h for h in have)
    # A reading stamped 1 us off its pose.
    o3 = TeamObserver("agent_0", 3, 10)
    o3.add_map(_map(walls, Time(sec=1)))
    stamp = Time(sec=2)
    for j, cell in enumerate(cells):
        o3.add_pose(IDS[j], messages.pose_msg(cell, stamp, GEO10))
        off = Time(sec=2, nanosec=1000) if j == 1 else stamp
        o3.add_reading(IDS[j], messages.reading_msg(IDS[j], 5.0, 0.0, off))
    o3.add_status(messages.status_msg(IDS, 0, 0, stamp, Time(sec=1)))
    need, have = o3.waiting_for()
    assert need == ["the reading of agent_1 stamped 2.000000000"]
    assert have == ["latest reading of agent_1 stamped 2.000001000 (+1.000 us from the status)"]
    # Poses and readings with no status for them.
    o4 = TeamObserver("agent_0", 3, 10)
    for j, cell in enumerate(cells):
        o4.add_pose(IDS[j], messages.pose_msg(cell, stamp, GEO10))
        o4.add_reading(IDS[j], messages.reading_msg(IDS[j], 5.0, 0.0, stamp))
    assert o4.orphan_round() == 2_000_000_000


def test_observer_takes_the_grid_from_the_map():
    """Origin and resolution come from the OccupancyGrid; walls as 1 are free, and said so."""
    walls = torch.zeros((10, 10), dtype=torch.bool)
    walls[0, 4] = True
    geo = GridGeometry(10, 10, 2.5, origin_x=-12.5, origin_y=40.0)
    o = TeamObserver("agent_0", 3, 10)
    o.add_map(_map(walls, Time(sec=1), resolution=2.5, origin=(-12.5, 40.0)))
    assert not o.notes
    _round(o, [(0, 3), (2, 2), (9, 9)], Time(sec=2), 0, 0, Time(sec=1), geo)
    _, mask, _ = o.observe()
    assert not bool(mask[2])  # E of (0, 3) is the wall at (0, 4)
    o.add_status(messages.status_msg(IDS, 0, 1, Time(sec=3), Time(sec=1)))  # step 1 names the map
    with pytest.raises(ValueError, match="outside"):
        o.add_pose("agent_1", messages.pose_msg((1, 1), Time(sec=3), GEO10))  # at the wrong origin
    faint = _map(walls, Time(sec=5))
    faint.data = [1 if v else 0 for v in faint.data]
    o.add_map(faint)
    assert "1 cells valued 1..49: they are free" in o.notes[-1]
    other = _map(walls, Time(sec=6))
    other.header.frame_id = "world"
    with pytest.raises(ValueError, match="frame 'world'"):
        o.add_map(other)
    strict = TeamObserver("agent_0", 3, 10, resolution=1.0)
    with pytest.raises(ValueError, match="resolution"):
        strict.add_map(_map(walls, Time(sec=1), resolution=2.5))
