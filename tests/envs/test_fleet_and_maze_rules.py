"""Fleet coordination and maze cleaning: the rules a user would notice."""

from __future__ import annotations

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.fleet_coordination import (
    DELIVERED,
    DELIVERY_BONUS,
    PICKUP_REWARD,
    RIDING,
    TIME_COST,
    WAITING,
)
from medc_training.envs.grid import bfs_distance
from medc_training.envs.maze_cleaning import CLEAN_REWARD, generate_mazes
from medc_training.envs.maze_cleaning import TIME_COST as MAZE_TIME_COST


def _fleet(**kw):
    env = make_batched(
        "fleet_coordination", num_envs=1, seed=0, agents=2, customers=3, capacity=1, grid=6, **kw
    )
    env.reset()
    return env


def _place(env, vehicles, origins, dests):
    env.positions[0] = torch.tensor(vehicles)
    env.origin[0] = torch.tensor(origins)
    env.destination[0] = torch.tensor(dests)
    env.status[0] = WAITING
    env.carrier[0] = -1
    from medc_training.envs.grid import move_mask

    env.mask = move_mask(env.positions, env.blocked_pad, env._deltas)


def test_fleet_pickup_capacity_drop_and_delivery_bonus() -> None:
    env = _fleet()
    # Vehicle 0 at (2,2) next to two customers waiting at (2,3); vehicle 1 far away.
    _place(env, [[2, 2], [5, 5]], [[2, 3], [2, 3], [0, 0]], [[2, 5], [4, 3], [0, 2]])
    east, west, stay_ish = 2, 6, 0
    out = env.step(torch.tensor([[east, stay_ish]]))
    # Capacity 1: only the lowest-index customer boards.
    assert env.status[0].tolist() == [RIDING, WAITING, WAITING] and env.carrier[0, 0] == 0
    assert float(out.reward[0]) == pytest.approx(PICKUP_REWARD - TIME_COST)
    obs = out.obs[0, 0]
    assert obs[4, 2, 5] == 1 and obs[4].sum() == 1  # own passenger's destination
    assert obs[5].mean() == pytest.approx(1.0)  # full
    assert out.obs[0, 1, 4].sum() == 0 and out.obs[0, 1, 5].sum() == 0
    env.step(torch.tensor([[east, west]]))
    out = env.step(torch.tensor([[east, west]]))
    assert env.status[0, 0] == DELIVERED
    assert float(out.reward[0]) == pytest.approx(-TIME_COST)
    assert not out.done[0]


def test_fleet_terminates_when_all_delivered_with_bonus() -> None:
    env = _fleet()
    _place(env, [[0, 0], [5, 5]], [[0, 1], [5, 4], [5, 4]], [[0, 2], [5, 3], [5, 2]])
    env.step(torch.tensor([[2, 6]]))  # both pick up
    env.step(torch.tensor([[2, 6]]))  # 0 drops; 1 drops first customer at (5,3)
    assert env.status[0].tolist() == [DELIVERED, DELIVERED, WAITING]
    env.step(torch.tensor([[4, 2]]))  # 1 goes back to (5,4) and boards the last one
    out = env.step(torch.tensor([[0, 6]]))
    out = env.step(torch.tensor([[0, 6]]))
    assert bool(out.terminated[0]) and bool(out.success[0]) and not bool(out.truncated[0])
    assert float(out.reward[0]) == pytest.approx(DELIVERY_BONUS - TIME_COST)
    assert int(out.episode_length[0]) == 5
    assert (env.status[0] == WAITING).all()  # auto-reset


@pytest.mark.parametrize("name", ["fleet_coordination", "maze_cleaning"])
def test_oracle_finishes_episodes_and_random_play_truncates(name: str) -> None:
    env = make_batched(name, num_envs=16, seed=1, max_steps=100)
    env.reset()
    finished = []
    for _ in range(100):
        out = env.step(env.oracle_action_scores().argmax(-1))
        finished += out.success[out.done].tolist()
    assert len(finished) >= 16 and all(finished)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(100):
        out = env.step(torch.multinomial(env.mask.view(-1, 8).float(), 1, generator=gen).view(16, -1))
    assert out.truncated.all() and not out.terminated.any()


@pytest.mark.parametrize("complexity", [1.0, 0.5, 0.0])
@pytest.mark.parametrize("grid", [7, 10])
def test_mazes_are_connected_and_complexity_removes_walls(grid: int, complexity: float) -> None:
    gen = torch.Generator().manual_seed(0)
    walls = generate_mazes(32, grid, complexity, gen, torch.device("cpu"))
    src = torch.zeros_like(walls)
    src[:, 0, 0] = True
    d = bfs_distance(~walls, src)
    assert not (torch.isinf(d) & ~walls).any()
    if complexity == 1.0:
        # Perfect maze: the rooms form a tree, so free cells = 2 * rooms - 1 (rooms + openings).
        rooms = ((grid + 1) // 2) ** 2
        assert ((~walls).flatten(1).sum(1) == 2 * rooms - 1).all()


def test_maze_cleaning_rewards_each_cleaned_cell() -> None:
    env = make_batched("maze_cleaning", num_envs=32, seed=3, agents=2, grid=9)
    env.reset()
    dirty_before = env.dirty.flatten(1).sum(1)
    acts = env.oracle_action_scores().argmax(-1)
    out = env.step(acts)
    cleaned = dirty_before - env.dirty.flatten(1).sum(1)
    ongoing = ~out.done
    assert (cleaned[ongoing] >= 1).all()
    expected = CLEAN_REWARD * cleaned.float() - MAZE_TIME_COST
    assert torch.allclose(out.reward[ongoing], expected[ongoing])
    # Agents never stand on walls, and the dirty map never marks a wall.
    assert not (env.dirty & env.walls).any()
    cells = env.positions[..., 0] * 9 + env.positions[..., 1]
    assert not env.walls.flatten(1).gather(1, cells).any()
