"""Batched target-localization core: shapes, masks, auto-reset, incremental observations."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.target_localization import build_observations


def _random_valid_actions(mask: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    b, n, a = mask.shape
    return torch.multinomial(mask.view(-1, a).float(), 1, generator=gen).view(b, n)


@pytest.mark.parametrize("copy_obs", [True, False])
def test_step_shapes_and_incremental_obs_match_full_rebuild(copy_obs: bool) -> None:
    env = make_batched(
        "target_localization", num_envs=8, seed=3, agents=3, walls=2, grid=12, max_steps=15,
        copy_obs=copy_obs, observation="maps",
    )
    obs, mask = env.reset()
    assert obs.shape == (8, 3, 5, 12, 12) and obs.dtype == torch.float32
    assert mask.shape == (8, 3, 8) and mask.dtype == torch.bool
    gen = torch.Generator().manual_seed(0)
    finished = 0
    for _ in range(40):
        out = env.step(_random_valid_actions(mask, gen))
        mask = out.mask
        ref = build_observations(env.positions, env.reading_map, env.visit_map, env.walls)
        assert torch.equal(out.obs, ref)
        assert out.reward.shape == (8,) and out.terminated.dtype == torch.bool
        finished += int(out.done.sum())
    assert finished > 0
