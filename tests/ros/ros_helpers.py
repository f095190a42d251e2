"""Helpers shared by the ROS graph tests (imported by name; tests/ros is on sys.path)."""

from __future__ import annotations

from pathlib import Path


def training_env(*, seed: int, agents: int, walls: int, grid: int, max_steps: int, observation: str = "maps"):
    """The noise-free target-localization core (B = 1) that the simulator node runs, producing the
    observation a policy takes."""
    from medc_training.envs import make_batched

    return make_batched("target_localization", num_envs=1, device="cpu", seed=seed, agents=agents,
                        walls=walls, grid=grid, max_steps=max_steps, reward_shaping=False, noise=False,
                        observation=observation)


def reference_episodes(
    bundle: Path, episodes: int, *, seed: int, agents: int, walls: int, grid: int, max_steps: int
):
    """Play ``episodes`` with the training environment and ``bundle`` greedy, as training would.

    Returns (lengths, successes, trace) with trace = [(episode, step, actions)] like SimCore.trace.
    """
    import torch
    from medc_training.bundle import load_bundle

    policy = load_bundle(bundle)
    env = training_env(seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps,
                       observation=policy.observation)
    obs, mask = env.reset()
    lengths, successes, trace, step = [], [], [], 0
    with torch.no_grad():
        while len(lengths) < episodes:
            actions = policy.act(obs[0], mask[0], greedy=True)
            trace.append((len(lengths), step, [int(a) for a in actions]))
            out = env.step(actions.unsqueeze(0))
            obs, mask, step = out.obs, out.mask, step + 1
            if bool(out.terminated[0] | out.truncated[0]):
                lengths.append(int(out.episode_length[0]))
                successes.append(bool(out.success[0]))
                step = 0
    return lengths, successes, trace


def spin_until(executor, condition, timeout_s: float) -> bool:
    """Spin ``executor`` until ``condition()`` holds; False on timeout."""
    import time

    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def replay_masks(trace, *, seed: int, agents: int, walls: int, grid: int, max_steps: int):
    """The move masks [N,A] the agents had at each step of ``trace``, by replaying it in the env."""
    import torch

    env = training_env(seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps)
    _, mask = env.reset()
    masks = []
    for _, _, actions in trace:
        masks.append(mask[0].clone())
        mask = env.step(torch.tensor([actions])).mask
    return masks
