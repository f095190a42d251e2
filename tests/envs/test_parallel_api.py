"""PettingZoo conformance of every application, and the wrapper following its batched core."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from env_scenarios import SMALL
from medc_training.envs import ENV_NAMES, make_batched, make_env
from pettingzoo.test import parallel_api_test, parallel_seed_test


def test_parallel_api(name: str) -> None:
    parallel_api_test(make_env(name, seed=0, **SMALL[name]), num_cycles=200)


def test_parallel_seed(name: str) -> None:
    parallel_seed_test(lambda: make_env(name, **SMALL[name]), num_cycles=100)


def test_spaces_are_the_same_object_and_obs_fit_them(name: str) -> None:
    env = make_env(name, seed=1, **SMALL[name])
    obs, _ = env.reset()
    for agent in env.possible_agents:
        assert env.observation_space(agent) is env.observation_space(agent)
        assert env.action_space(agent) is env.action_space(agent)
        assert env.observation_space(agent).contains(obs[agent])


def test_wrapper_equals_batched_core_step_for_step(name: str) -> None:
    """Same seed, same actions: the B=1 core and the ParallelEnv agree, across episode ends."""
    core = make_batched(name, num_envs=1, seed=7, **SMALL[name])
    env = make_env(name, seed=7, **SMALL[name])
    obs_c, mask_c = core.reset()
    obs_e, _ = env.reset()
    rng = np.random.default_rng(0)
    episodes = 0
    for _ in range(120):
        for i, agent in enumerate(env.possible_agents):
            np.testing.assert_array_equal(obs_e[agent]["observation"], obs_c[0, i].numpy())
            np.testing.assert_array_equal(obs_e[agent]["action_mask"], mask_c[0, i].numpy().astype(np.int8))
        acts = rng.integers(0, core.num_actions, size=core.num_agents)
        out = core.step(torch.from_numpy(acts).unsqueeze(0))
        obs_e, rew, term, trunc, _ = env.step({a: int(acts[i]) for i, a in enumerate(env.possible_agents)})
        assert all(r == pytest.approx(float(out.reward[0])) for r in rew.values())
        assert all(t == bool(out.terminated[0]) for t in term.values())
        assert all(t == bool(out.truncated[0]) for t in trunc.values())
        if out.done[0]:
            episodes += 1
            for i, agent in enumerate(env.possible_agents):
                np.testing.assert_array_equal(obs_e[agent]["observation"], out.final_obs[0, i].numpy())
            assert env.agents == []
            obs_e, _ = env.reset()
        obs_c, mask_c = out.obs, out.mask
    assert episodes >= 2


def test_render_rgb_array(name: str) -> None:
    env = make_env(name, seed=2, render_mode="rgb_array", **SMALL[name])
    env.reset()
    frame = env.render()
    grid = SMALL[name]["grid"]
    assert frame.dtype == np.uint8 and frame.shape == (grid * 16, grid * 16, 3)
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 3


def test_save_observation_png(name: str, tmp_path) -> None:
    from matplotlib.image import imread
    from medc_training.envs.render import save_observation_png

    env = make_env(name, seed=2, **SMALL[name])
    obs, _ = env.reset()
    path = save_observation_png(obs["agent_0"]["observation"], tmp_path / "obs.png", application=name)
    img = imread(path)
    assert img.shape[1] > img.shape[0] > 100


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"agents": 0}, "agents"),
        ({"grid": 3}, "grid"),
        ({"walls": 99}, "walls"),
        ({"max_steps": 0}, "max_steps"),
        ({"reward_shaping": "yes"}, "reward_shaping"),
        ({"colour": 3}, "allowed options"),
        ({"device": "tpu9"}, "device"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_target_localization_options_raise_value_error(options: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        make_env("target_localization", **options)


@pytest.mark.parametrize(
    ("name", "options", "words"),
    [
        ("fleet_coordination", {"customers": 0}, "customers"),
        ("fleet_coordination", {"capacity": 0}, "capacity"),
        ("fleet_coordination", {"agents": 0}, "agents"),
        ("fleet_coordination", {"walls": 2}, "allowed options"),
        ("maze_cleaning", {"complexity": 1.5}, "complexity"),
        ("maze_cleaning", {"grid": 2}, "grid"),
        ("maze_cleaning", {"agents": 0}, "agents"),
    ],
)
def test_bad_fleet_and_maze_options_raise_value_error(name: str, options: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        make_env(name, **options)


def test_every_application_describes_itself() -> None:
    assert set(make_batched("target_localization").attributes) == {"agents", "walls", "grid", "max_steps"}
    assert make_batched("fleet_coordination").attributes == {
        "agents": 3,
        "customers": 8,
        "capacity": 2,
        "grid": 10,
        "max_steps": 100,
    }
    assert make_batched("maze_cleaning", complexity=0.5).attributes == {
        "agents": 3,
        "grid": 10,
        "complexity": 0.5,
        "max_steps": 100,
    }


def test_cuda_device_works_or_is_refused_clearly() -> None:
    if torch.cuda.is_available():
        env = make_batched("target_localization", num_envs=4, device="cuda", seed=0, grid=10, walls=1)
        obs, mask = env.reset()
        out = env.step(env.oracle_action_scores().argmax(-1))
        assert obs.device.type == out.obs.device.type == mask.device.type == "cuda"
    else:
        with pytest.raises(ValueError, match="CUDA is not available"):
            make_batched("target_localization", device="cuda")


def test_bad_name_and_render_mode_raise_value_error() -> None:
    with pytest.raises(ValueError, match="target_localization"):
        make_env("pong")
    with pytest.raises(ValueError, match="rgb_array"):
        make_env("target_localization", render_mode="human")


def test_render_command_writes_area_and_maps_for_every_application(tmp_path) -> None:
    from medc_training.cli.pictures import main

    assert main([str(tmp_path), "--steps", "3"]) == 0
    written = sorted(p.name for p in tmp_path.glob("*.png"))
    assert written == sorted(f"{n}_{kind}.png" for n in ENV_NAMES for kind in ("area", "agent_0"))


def test_cores_create_every_tensor_on_their_own_device(name: str) -> None:
    """With the default device set elsewhere ("meta"), a tensor made without device= would
    break the CPU run: this is how the CUDA path stays correct without a GPU here."""
    torch.set_default_device("meta")
    try:
        extra = {"reward_shaping": True, "noise": True} if name == "target_localization" else {}
        env = make_batched(name, num_envs=4, device="cpu", seed=0, **SMALL[name], **extra)
        env.reset()
        for _ in range(45):
            out = env.step(env.oracle_action_scores().argmax(-1))
        assert out.obs.device.type == out.final_obs.device.type == out.reward.device.type == "cpu"
    finally:
        torch.set_default_device("cpu")
