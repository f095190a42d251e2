"""Fleet coordination and maze cleaning with an agent-centred observation (``observation="egoR"``)."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched, make_env
from pettingzoo.test import parallel_api_test


@pytest.mark.parametrize(("name", "walls_channel"), [("fleet_coordination", None), ("maze_cleaning", 3)])
def test_ego_window_is_the_maps_around_the_agent(name, walls_channel):
    env = make_batched(name, num_envs=3, seed=2, agents=3, grid=8, max_steps=30, observation="ego3")
    obs, _ = env.reset()
    maps = env.picture_maps(0)  # [N,C,G,G] absolute maps of environment 0
    assert obs.shape == (3, 3, maps.shape[1], 7, 7) and env.obs_shape == (maps.shape[1], 7, 7)
    for i, (r, c) in enumerate(env.positions[0].tolist()):
        win = obs[0, i]
        for dr in range(-3, 4):
            for dc in range(-3, 4):
                rr, cc = r + dr, c + dc
                inside = 0 <= rr < 8 and 0 <= cc < 8
                assert win[0, dr + 3, dc + 3] == (0.0 if inside else 1.0)  # channel 0: off the grid
                for ch in range(1, maps.shape[1]):
                    want = maps[i, ch, rr, cc] if inside else (1.0 if ch == walls_channel else 0.0)
                    assert win[ch, dr + 3, dc + 3] == want


@pytest.mark.parametrize("name", ["fleet_coordination", "maze_cleaning"])
def test_ego_parallel_env_passes_the_api_test_and_renders(name):
    env = make_env(name, seed=1, agents=2, grid=6, max_steps=20, observation="ego5", render_mode="rgb_array")
    parallel_api_test(env, num_cycles=60)
    env.reset(seed=3)
    assert env.render().shape == (6 * 16, 6 * 16, 3)


def test_ego_bundle_round_trip_names_its_observation():
    from medc_training.bundle import BundleError, bundle_bytes, load_bundle
    from medc_training.evaluate import env_for_bundle
    from medc_training.nets import make_actor_critic
    from medc_training.runner import observation_section

    env = make_batched("maze_cleaning", num_envs=2, seed=0, agents=2, grid=8, observation="ego4")
    net = make_actor_critic("mlp", env.obs_shape, 8)
    manifest = {"application": env.name, "environment": env.attributes, **observation_section(env)}
    bundle = load_bundle(bundle_bytes(net, manifest))
    assert bundle.observation == "ego4" and bundle.manifest["observation"]["channel_names"][0] == "off_grid"
    again = env_for_bundle(bundle, num_envs=2)
    assert again.obs_shape == env.obs_shape
    obs, mask = again.reset(seed=1)
    assert bundle.act(obs.flatten(0, 1), mask.flatten(0, 1)).shape == (4,)
    with pytest.raises(BundleError, match="'ego3' is 7x7 here"):
        bad = {**manifest, "observation": {"name": "ego3"}}
        bundle_bytes(net, bad)
    assert torch.equal(make_batched("maze_cleaning", num_envs=1, seed=0).reset()[0],
                       make_batched("maze_cleaning", num_envs=1, seed=0, observation="maps").reset()[0])
