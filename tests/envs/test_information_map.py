"""The ``+information`` views: at each cell the team can stand on next, the share of a reading's
variance the unknown source cell explains, Var / (E + Var), from the team's own posterior; the
native pass equals the torch reference; the channel comes last and the ROS agent's memory builds the
same observation as the training core."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched, tl_native
from medc_training.envs.grid import action_deltas
from medc_training.envs.tl_observation import INFORMATION_CHANNEL, observation_channels, parse_observation
from medc_training.envs.tl_sensing import geometric_factor

VIEW = "ego6+estimate+posterior+information"


def _world(observation: str = VIEW, num_envs: int = 6, seed: int = 5):
    env = make_batched("target_localization", num_envs=num_envs, seed=seed, world="radbench", agents=3,
                       walls=7, grid=20, max_steps=120, sensing="realistic", observation=observation)
    env.reset()
    g = torch.Generator().manual_seed(seed)
    for _ in range(4):
        env.step(torch.randint(0, 8, (num_envs, 3), generator=g))
    return env


def _reference(env) -> torch.Tensor:
    """The map from its definition, cell by cell, with the sensing model's own geometric factor."""
    m, est, g = env.memory, env.memory.estimator, env.grid
    p = m.posterior()
    phys = m.log_post.transpose(1, 2)
    w = phys.double().exp().sum(1)
    w = w / w.sum(1, keepdim=True)
    strength = (w @ est.level_strength.double()).float()
    background = (w @ est.level_background.double()).float()
    walls = env.walls_f > 0.5
    out = torch.zeros((env.num_envs, g * g))
    steps = torch.cat((torch.zeros((1, 2), dtype=torch.long), action_deltas("cpu")))
    for k in range(env.num_envs):
        near = (env.positions[k].unsqueeze(1) + steps).clamp(0, g - 1).view(-1, 2)
        cells = {tuple(c) for c in near.tolist()}
        for r, c in cells:
            if walls[k, r, c]:
                continue
            f = geometric_factor(m.sensing, torch.tensor([[[r, c]]]), est.cells, walls[k:k + 1],
                                 m.rects[k:k + 1])[0, 0]
            mean_f, square_f = float((p[k] * f).sum()), float((p[k] * f * f).sum())
            var = float(strength[k]) ** 2 * max(square_f - mean_f**2, 0.0)
            mean = float(strength[k]) * mean_f + float(background[k])
            out[k, r * g + c] = var / (mean + var)
    return out.view(-1, g, g)


def test_the_view_parses_names_its_channel_last_and_needs_the_source_estimate():
    spec = parse_observation(VIEW)
    assert spec.information and spec.name == VIEW
    assert observation_channels(VIEW)[-1] == INFORMATION_CHANNEL
    assert parse_observation("maps+information").information
    with pytest.raises(ValueError, match="information last"):
        parse_observation("ego6+information+posterior")
    with pytest.raises(ValueError, match="no source estimate"):
        make_batched("fleet_coordination", num_envs=1, seed=0, observation="ego6+information")


@pytest.mark.parametrize("native", [True, False])
def test_the_map_is_the_variance_share_at_the_cells_the_team_can_stand_on_next(native):
    env = _world()
    if native and not tl_native.usable(torch.zeros(1)):
        pytest.skip("no native kernel on this machine")
    if native:
        got = env.memory.information_map(env.positions, env.walls_f)
    else:
        with tl_native.turned_off():
            got = env.memory.information_map(env.positions, env.walls_f)
    want = _reference(env)
    assert torch.allclose(got, want, atol=1e-5), (got - want).abs().max()
    assert bool((got >= 0).all()) and bool((got < 1).all()) and float(got.max()) > 0.05
    # nothing away from the team's next cells: at most 27 cells an episode are non-zero
    assert int((got > 0).sum((1, 2)).max()) <= 27
    obs = env.memory.observe(env.positions, env.walls_f)  # [B, N, C, 13, 13], the agent at the centre
    centre = obs[:, :, -1, 6, 6]
    k = env.positions.shape[0]
    at = got.view(k, -1).gather(1, env.positions[..., 0] * env.grid + env.positions[..., 1])
    assert torch.allclose(centre, at)


def test_a_reading_where_every_hypothesis_agrees_tells_nothing():
    env = _world()
    m = env.memory
    fixed = torch.zeros_like(m.posterior())
    fixed[:, 0] = 1.0  # a posterior sure of one cell: every reading's rate is known
    m._keep_posterior(fixed)
    assert float(m.information_map(env.positions, env.walls_f).abs().max()) < 1e-6
