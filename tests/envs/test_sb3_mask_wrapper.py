"""MaskableVecEnv: the batched core in SB3's VecEnv interface with sb3-contrib's
``action_masks()``. SB3 is not a dependency here, so its contract is tested directly (the
calls MaskablePPO makes); with sb3-contrib installed a short MaskablePPO run is added."""

from __future__ import annotations

import numpy as np
import pytest
from medc_training.envs import make_batched, make_env
from medc_training.envs.sb3 import MaskableVecEnv

OPTIONS = dict(agents=3, walls=2, grid=12, max_steps=10)


def _masked_random(env: MaskableVecEnv, rng: np.random.Generator) -> np.ndarray:
    masks = np.stack(env.env_method("action_masks"))  # sb3_contrib.common.maskable.utils.get_action_masks
    return np.array([rng.choice(np.flatnonzero(m)) for m in masks])


def test_slots_are_agents_of_environments_with_their_masks():
    env = MaskableVecEnv(num_envs=2, seed=5, **OPTIONS)
    obs = env.reset()
    assert env.num_envs == 6 and obs.shape == (6, *env.observation_space.shape)
    assert env.observation_space.contains(obs[0]) and env.action_space.n == 8
    # Slot k = agent k % N of environment k // N: the core's own layout, same seed.
    core = make_batched("target_localization", num_envs=2, seed=5, **OPTIONS)
    ref_obs, ref_mask = core.reset(seed=5)
    np.testing.assert_array_equal(obs, ref_obs.reshape(6, *ref_obs.shape[2:]).numpy())
    masks = env.action_masks()
    assert masks.dtype == bool and masks.shape == (6, 8)
    np.testing.assert_array_equal(masks, ref_mask.reshape(6, 8).numpy())
    np.testing.assert_array_equal(np.stack(env.env_method("action_masks")), masks)
    assert [m.tolist() for m in env.env_method("action_masks", indices=[4])] == [masks[4].tolist()]
    assert len(env.get_attr("action_masks")) == 6  # is_masking_supported() asks this
    with pytest.raises(AttributeError):
        env.get_attr("no_such_thing")
    # A parallel env of the same seed starts where environment 0 does.
    par_obs, _ = make_env("target_localization", seed=5, **OPTIONS).reset(seed=5)
    np.testing.assert_array_equal(par_obs["agent_1"]["observation"], obs[1])
    np.testing.assert_array_equal(par_obs["agent_1"]["action_mask"].astype(bool), masks[1])


def test_episodes_end_per_environment_with_monitor_infos():
    env = MaskableVecEnv(num_envs=3, seed=1, **OPTIONS)
    rng = np.random.default_rng(0)
    env.reset()
    finished = []
    team_return = np.zeros(3)
    for _ in range(40):
        actions = _masked_random(env, rng)
        obs, rewards, dones, infos = env.step(actions)
        assert obs.shape[0] == rewards.shape[0] == dones.shape[0] == len(infos) == 9
        per_env = rewards.reshape(3, 3)
        assert (per_env == per_env[:, :1]).all(), "every agent of an environment gets the team reward"
        team_return += per_env[:, 0]
        for b in range(3):
            slots = dones[3 * b:3 * b + 3]
            assert slots.all() or not slots.any(), "an environment's agents end their episode together"
            if slots.any():
                info = infos[3 * b]
                assert info["terminal_observation"].shape == env.observation_space.shape
                assert info["episode"]["l"] <= OPTIONS["max_steps"]
                assert info["episode"]["r"] == pytest.approx(team_return[b], rel=1e-5)
                assert info["TimeLimit.truncated"] == (not info["is_success"])
                finished.append(info["episode"])
                team_return[b] = 0.0
    assert len(finished) >= 3


def test_masked_moves_are_the_ones_that_do_nothing():
    """The mask means what MaskablePPO assumes: a masked move cannot be taken (it leaves the agent
    in place), an allowed one is taken."""
    env = MaskableVecEnv(num_envs=1, seed=2, agents=1, walls=1, grid=6, max_steps=200)
    env.reset()
    rng = np.random.default_rng(1)
    moved = stayed = 0
    for t in range(120):
        mask = env.action_masks()[0]
        before = env.core.state(0).positions[0]
        blocked = np.flatnonzero(~mask)
        take_blocked = blocked.size > 0 and t % 2 == 0
        action = int(rng.choice(blocked if take_blocked else np.flatnonzero(mask)))
        _, _, done, _ = env.step(np.array([action]))
        if done[0]:
            continue
        after = env.core.state(0).positions[0]
        if take_blocked:
            assert after == before, f"masked move {action} moved the agent"
            stayed += 1
        else:
            assert after != before, f"allowed move {action} did not move the agent"
            moved += 1
    assert moved > 5 and stayed > 5


def test_maskable_ppo_learns_a_few_steps_when_installed():
    sb3_contrib = pytest.importorskip("sb3_contrib")
    env = MaskableVecEnv(num_envs=2, seed=0, **OPTIONS)
    model = sb3_contrib.MaskablePPO("MlpPolicy", env, n_steps=16, batch_size=32, n_epochs=1, seed=0)
    model.learn(total_timesteps=96)
    obs = env.reset()
    actions, _ = model.predict(obs, action_masks=env.action_masks())
    assert env.action_masks()[np.arange(len(actions)), actions].all()
