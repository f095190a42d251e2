"""The pure observation functions the ROS agent node reuses, on hand-built data; seeding."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.target_localization import (
    BACKGROUND,
    SOURCE_STRENGTH,
    VISIT_SATURATION,
    build_observations,
    normalise_reading,
    sensor_reading,
    update_memory,
)


def test_update_memory_and_build_observations_on_hand_built_team() -> None:
    reading_map = torch.zeros(1, 6, 6)
    visit_map = torch.zeros(1, 6, 6)
    walls = torch.zeros(1, 6, 6, dtype=torch.bool)
    walls[0, 3, 1:4] = True
    positions = torch.tensor([[[0, 0], [5, 5], [0, 0]]])  # agents 0 and 2 share a cell
    update_memory(reading_map, visit_map, positions, torch.tensor([[10.0, 100.0, 10.0]]))
    positions2 = torch.tensor([[[0, 1], [5, 5], [1, 0]]])
    update_memory(reading_map, visit_map, positions2, torch.tensor([[20.0, 50.0, 30.0]]))
    obs = build_observations(positions2, reading_map, visit_map, walls)
    assert obs.shape == (1, 3, 5, 6, 6)
    # Own location: exactly one cell each.
    for i, (r, c) in enumerate(positions2[0].tolist()):
        assert obs[0, i, 0].sum() == 1 and obs[0, i, 0, r, c] == 1
    # Team locations: the other two agents' cells, not one's own.
    assert obs[0, 0, 1].sum() == 2 and obs[0, 0, 1, 5, 5] == 1 and obs[0, 0, 1, 1, 0] == 1
    # Readings: the latest reading per visited cell, normalised, shared by the team.
    assert obs[0, 1, 2, 5, 5] == pytest.approx(float(normalise_reading(torch.tensor(50.0))))
    assert obs[0, 1, 2, 0, 0] == pytest.approx(float(normalise_reading(torch.tensor(10.0))))
    assert obs[0, 1, 2, 2, 2] == 0  # never visited
    assert torch.equal(obs[0, 0, 2], obs[0, 2, 2])
    # Visit counts: (0,0) twice, (5,5) twice, (0,1) and (1,0) once.
    assert obs[0, 0, 3, 0, 0] == pytest.approx(2 / VISIT_SATURATION)
    assert obs[0, 0, 3, 0, 1] == pytest.approx(1 / VISIT_SATURATION)
    assert obs[0, 0, 3].sum() == pytest.approx(6 / VISIT_SATURATION)
    # Walls.
    assert torch.equal(obs[0, 1, 4].bool(), walls[0])
    assert obs.min() >= 0 and obs.max() <= 1


def test_normalised_reading_is_monotone_and_bounded() -> None:
    raw = torch.tensor([0.0, BACKGROUND, 10.0, 100.0, SOURCE_STRENGTH + BACKGROUND, 1e6])
    norm = normalise_reading(raw)
    assert (norm[1:] >= norm[:-1]).all() and norm[0] == 0 and norm[-2] == pytest.approx(1.0)
    assert norm.max() <= 1.0


def test_core_records_exactly_its_readings() -> None:
    env = make_batched("target_localization", num_envs=4, seed=0, grid=10, walls=1, noise=True)
    env.reset()
    env.step(env.oracle_action_scores().argmax(-1))
    exact = sensor_reading(env.positions, env.target, env.walls)
    assert torch.equal(env.readings, env.readings.round())  # Poisson counts
    assert not torch.equal(env.readings, exact)
    cells = env.positions[..., 0] * 10 + env.positions[..., 1]
    recorded = env.reading_map.view(4, -1).gather(1, cells)
    assert torch.allclose(recorded, normalise_reading(env.readings))


@pytest.mark.parametrize("name", ["target_localization", "fleet_coordination", "maze_cleaning"])
def test_same_seed_same_episodes_other_seed_other_episodes(name: str) -> None:
    def rollout(seed: int) -> list[torch.Tensor]:
        env = make_batched(name, num_envs=4, seed=seed, max_steps=10)
        obs, _ = env.reset()
        seen = [obs]
        for _ in range(25):
            out = env.step(env.oracle_action_scores().argmax(-1))
            seen.append(out.obs)
        return seen

    a, b, c = rollout(11), rollout(11), rollout(12)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))
