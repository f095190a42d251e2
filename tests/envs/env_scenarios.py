"""Small scenarios of the three applications, shared by the environment tests (quick to step,
still with walls, several customers, a maze)."""

from __future__ import annotations

SMALL = {
    "target_localization": {"agents": 3, "walls": 2, "grid": 12, "max_steps": 40},
    "fleet_coordination": {"agents": 3, "customers": 4, "capacity": 2, "grid": 6, "max_steps": 40},
    "maze_cleaning": {"agents": 2, "grid": 7, "max_steps": 40},
}


def estimator_trace(sensing: str, grid: int, path: str, steps: int = 100, batch: int = 24) -> list[tuple]:
    """(observation, posterior, mask) after the reset and each of ``steps`` random valid team moves of a
    target-localization batch whose estimators take ``path`` (``tl_observation.ESTIMATOR_PATHS``):
    the same seeds, so the same episodes, whichever path."""
    import torch
    from medc_training.envs import make_batched
    from medc_training.envs.tl_observation import estimator_path

    with estimator_path(path):
        env = make_batched("target_localization", num_envs=batch, seed=11, agents=3, walls=2, grid=grid,
                           max_steps=40, sensing=sensing, observation="ego6+estimate", posterior=True)
    gen = torch.Generator().manual_seed(4)
    obs, mask = env.reset()
    seen = [(obs.clone(), env.memory.posterior(), mask.clone())]
    for _ in range(steps):
        b, n, a = mask.shape
        out = env.step(torch.multinomial(mask.view(-1, a).float(), 1, generator=gen).view(b, n))
        obs, mask = out.obs, out.mask
        seen.append((obs.clone(), env.memory.posterior(), mask.clone()))
    return seen
