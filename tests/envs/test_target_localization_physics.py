"""Target localization physics: readings, walls, masks, BFS, rewards, episode ends."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.grid import ACTIONS, bfs_distance, move_mask, pad_blocked
from medc_training.envs.target_localization import (
    BACKGROUND,
    SHAPING_SCALE,
    SOURCE_STRENGTH,
    SUCCESS_REWARD,
    WALL_ATTENUATION,
    generate_layouts,
    max_walls,
    sensor_reading,
)


def _reading(pos: tuple[int, int], target: tuple[int, int], walls: torch.Tensor) -> float:
    p = torch.tensor([[pos]], dtype=torch.long)
    t = torch.tensor([target], dtype=torch.long)
    return float(sensor_reading(p, t, walls.unsqueeze(0))[0, 0])


def test_reading_matches_formula_and_falls_with_distance() -> None:
    walls = torch.zeros(20, 20, dtype=torch.bool)
    target = (10, 3)
    values = [_reading((10, 3 + d), target, walls) for d in range(0, 12)]
    assert all(a > b for a, b in itertools.pairwise(values))
    for d, v in enumerate(values):
        assert v == pytest.approx(SOURCE_STRENGTH / (1 + d * d) + BACKGROUND, rel=1e-5)
    # Diagonal distance is Euclidean: (3, 4) away is 5 cells.
    assert _reading((13, 7), target, walls) == pytest.approx(SOURCE_STRENGTH / 26 + BACKGROUND, rel=1e-5)


def test_each_wall_crossed_lowers_the_reading() -> None:
    target, sensor = (10, 2), (10, 17)
    walls = torch.zeros(20, 20, dtype=torch.bool)
    free = _reading(sensor, target, walls)
    walls[5:15, 6] = True
    one = _reading(sensor, target, walls)
    walls[5:15, 12] = True
    two = _reading(sensor, target, walls)
    assert free > one > two
    base = SOURCE_STRENGTH / (1 + 15**2)
    assert one - BACKGROUND == pytest.approx(base * WALL_ATTENUATION, rel=1e-5)
    assert two - BACKGROUND == pytest.approx(base * WALL_ATTENUATION**2, rel=1e-5)
    # A wall that is not between source and sensor changes nothing.
    walls2 = torch.zeros(20, 20, dtype=torch.bool)
    walls2[0:3, 8] = True
    assert _reading(sensor, target, walls2) == pytest.approx(free)


def test_poisson_noise_has_the_exact_reading_as_mean() -> None:
    walls = torch.zeros(1, 10, 10, dtype=torch.bool)
    pos = torch.tensor([[[5, 8]] * 4000], dtype=torch.long)
    target = torch.tensor([[5, 5]])
    gen = torch.Generator().manual_seed(0)
    noisy = sensor_reading(pos, target, walls, noise=True, generator=gen)
    exact = SOURCE_STRENGTH / 10 + BACKGROUND
    assert torch.equal(noisy, noisy.round())  # counts
    assert float(noisy.mean()) == pytest.approx(exact, rel=0.02)
    assert float(noisy.std()) == pytest.approx(math.sqrt(exact), rel=0.1)


def test_mask_forbids_walls_and_off_grid_moves() -> None:
    walls = torch.zeros(1, 5, 5, dtype=torch.bool)
    walls[0, 1, 2] = True  # the cell north of (2, 2)
    deltas = torch.tensor(ACTIONS)
    corner = move_mask(torch.tensor([[[0, 0]]]), pad_blocked(walls), deltas)[0, 0]
    # From the top-left corner only E, SE, S stay on the grid.
    assert [i for i in range(8) if corner[i]] == [2, 3, 4]
    centre = move_mask(torch.tensor([[[2, 2]]]), pad_blocked(walls), deltas)[0, 0]
    assert not centre[0] and centre[1:].all()


def test_masked_move_leaves_agent_in_place() -> None:
    env = make_batched("target_localization", num_envs=16, seed=1, agents=2, walls=2, grid=10)
    _, mask = env.reset()
    before = env.positions.clone()
    bad = (~mask).float().argmax(-1)  # some invalid move where one exists
    has_bad = (~mask).any(-1)
    env.step(torch.where(has_bad, bad, mask.float().argmax(-1)))
    moved = (env.positions != before).any(-1)
    assert has_bad.any()
    assert not moved[has_bad & (env.t == 1).unsqueeze(1)].any()


def test_bfs_distance_goes_around_walls() -> None:
    free = torch.ones(1, 7, 7, dtype=torch.bool)
    free[0, 0:6, 3] = False  # a wall down column 3, open only at the bottom row
    src = torch.zeros_like(free)
    src[0, 0, 0] = True
    d = bfs_distance(free, src)[0]
    assert d[0, 0] == 0 and d[0, 2] == 2
    # (0, 4) is 4 columns away in a straight line, but the path goes down to row 6 and back.
    assert d[0, 4] == 12
    assert math.isinf(float(d[0, 3]))


@pytest.mark.parametrize("walls", [0, 1, 3])
def test_generated_walls_never_disconnect_free_cells(walls: int) -> None:
    gen = torch.Generator().manual_seed(walls)
    lay = generate_layouts(64, 12, walls, 3, gen, torch.device("cpu"))
    free = ~lay["walls"]
    assert not (torch.isinf(lay["distance"]) & free).any()
    assert (lay["walls"].flatten(1).sum(1) > 0).all() == (walls > 0)
    # Target and agents on distinct free cells.
    cells = torch.cat((lay["target"].unsqueeze(1), lay["positions"]), 1)
    flat = cells[..., 0] * 12 + cells[..., 1]
    assert all(len(set(row.tolist())) == 4 for row in flat)
    assert free.flatten(1).gather(1, flat).all()


def test_oracle_scores_are_minus_bfs_distance_and_reach_the_target() -> None:
    env = make_batched("target_localization", num_envs=32, seed=5, agents=2, walls=2, grid=12, max_steps=60)
    _, mask = env.reset()
    scores = env.oracle_action_scores()
    assert torch.isinf(scores[~mask]).all() and torch.isfinite(scores[mask]).all()
    successes = 0
    for _ in range(60):
        out = env.step(env.oracle_action_scores().argmax(-1))
        successes += int(out.success[out.done].sum())
        assert not out.truncated.any(), "greedy BFS descent always reaches the target in time"
    assert successes >= 32


def test_sparse_reward_termination_and_truncation() -> None:
    env = make_batched("target_localization", num_envs=64, seed=2, agents=1, walls=1, grid=10, max_steps=5)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    saw_trunc = saw_term = False
    for _ in range(20):
        acts = torch.multinomial(env.mask.view(-1, 8).float(), 1, generator=gen).view(64, 1)
        t_before = env.t.clone()
        out = env.step(acts)
        assert torch.equal(out.reward, out.terminated.float() * SUCCESS_REWARD)
        assert not (out.terminated & out.truncated).any()
        assert torch.equal(out.truncated, (t_before + 1 >= 5) & ~out.terminated)
        assert torch.equal(out.success, out.terminated)
        assert torch.equal(out.episode_length[out.done], (t_before + 1)[out.done])
        # Auto-reset: a finished environment starts again at t = 0.
        assert (env.t[out.done] == 0).all()
        saw_trunc |= bool(out.truncated.any())
        saw_term |= bool(out.terminated.any())
    assert saw_trunc and saw_term


def test_reward_shaping_rewards_getting_closer() -> None:
    env = make_batched(
        "target_localization", num_envs=32, seed=4, agents=1, walls=2, grid=12, reward_shaping=True
    )
    env.reset()
    scores = env.oracle_action_scores()
    closer = env.step(scores.argmax(-1))
    ongoing = ~closer.done
    assert torch.allclose(closer.reward[ongoing], torch.full_like(closer.reward[ongoing], SHAPING_SCALE))
    # Moving to the valid cell farthest from the target costs reward.
    away = env.oracle_action_scores()
    away = torch.where(torch.isinf(away), float("inf"), away).argmin(-1)
    farther = env.step(away)
    assert (farther.reward[~farther.done] < 0).all()


def test_max_walls_is_enforced() -> None:
    with pytest.raises(ValueError, match="walls"):
        make_batched("target_localization", grid=10, walls=max_walls(10) + 1)


def test_walls_only_ever_attenuate_readings_on_random_layouts() -> None:
    gen = torch.Generator().manual_seed(9)
    lay = generate_layouts(128, 16, 3, 4, gen, torch.device("cpu"))
    with_walls = sensor_reading(lay["positions"], lay["target"], lay["walls"])
    open_area = sensor_reading(lay["positions"], lay["target"], torch.zeros_like(lay["walls"]))
    assert (with_walls <= open_area + 1e-4).all()
    # The ratio (minus background) is a power of the attenuation: whole walls only.
    k = torch.log((with_walls - BACKGROUND) / (open_area - BACKGROUND)) / math.log(WALL_ATTENUATION)
    assert torch.allclose(k, k.round(), atol=1e-3)
    assert (k.round() > 0).any()


def test_mask_is_exactly_in_grid_and_free_on_random_layouts() -> None:
    env = make_batched("target_localization", num_envs=64, seed=8, agents=4, walls=3, grid=14)
    _, mask = env.reset()
    dest = env.positions.unsqueeze(2) + torch.tensor(ACTIONS)  # [B,N,A,2]
    inside = ((dest >= 0) & (dest < 14)).all(-1)
    clamped = dest.clamp(0, 13)
    free = ~env.walls[torch.arange(64).view(64, 1, 1), clamped[..., 0], clamped[..., 1]]
    assert torch.equal(mask, inside & free)
    assert not mask.all()  # some moves are blocked somewhere
