"""Obstructions as rectangles from a map (medc_training.envs.wall_cover): the cover is exact on any
map, takes one rectangle per separate obstruction, stays within its slots on touching and
overlapping obstructions, and the team's posterior started from it is the one started from the
obstructions' own rectangles."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from medc_training.envs.tl_observation import ObservationSpec, TeamMemory
from medc_training.envs.tl_sensing import wall_rectangles
from medc_training.envs.wall_cover import OBSTRUCTION_SLOTS, cover_cells, cover_rectangles
from medc_training.radbench.physics import TEAM_SENSING, episode_tensors, world_rates
from medc_training.radbench.scenario import Episode
from medc_training.radbench.sets import generate_file


def _union(rects, shape) -> np.ndarray:
    out = np.zeros(shape, dtype=bool)
    for r0, c0, r1, c1 in rects:
        out[r0:r1 + 1, c0:c1 + 1] = True
    return out


def _random_obstructions(rng, grid: int, count: int, span: int) -> list[tuple[int, int, int, int]]:
    """``count`` rectangles of 2-5 cells a side with their corners in the top-left ``span`` cells:
    a small span makes them touch and overlap."""
    out = []
    for _ in range(count):
        r0, c0 = (int(v) for v in rng.integers(0, span - 1, 2))
        h, w = (int(v) for v in rng.integers(2, 6, 2))
        out.append((r0, c0, min(r0 + h - 1, grid - 1), min(c0 + w - 1, grid - 1)))
    return out


def _slots_rects(rects, most: int) -> torch.Tensor:
    """(top, left, bottom, right) cell-centre rectangles of inclusive cell rectangles, ``most`` slots."""
    out = torch.full((most, 4), -1e6)
    out[:, 2:] = -1e6 - 1.0
    for k, (r0, c0, r1, c1) in enumerate(rects):
        out[k] = torch.tensor([r0 - 0.5, c0 - 0.5, r1 + 0.5, c1 + 0.5])
    return out


@pytest.mark.parametrize("cells", [
    ["#####", "#....", "#....", "#...."],  # an L
    ["#####", "..#..", "..#..", "..#.."],  # a T
    ["#####", "#...#", "#...#", "#####"],  # a ring round a hole
    ["##...", "###..", ".###.", "..###"],  # a staircase
    ["#####", "#####", "#####"],  # everything
    [".....", "....."],  # nothing
])
def test_the_cover_is_exactly_the_blocked_cells_of_any_shape(cells):
    walls = np.array([[ch == "#" for ch in row] for row in cells])
    rects = cover_cells(walls)
    assert (_union(rects, walls.shape) == walls).all()
    out = cover_rectangles(torch.from_numpy(walls)[None], 8)
    assert out.shape == (1, 8, 4) and out.dtype == torch.float32
    used = out[0, :, 2] > out[0, :, 0]
    assert int(used.sum()) == len(rects)
    blank = wall_rectangles(torch.zeros((1, 5, 5), dtype=torch.bool), 8)[0]
    assert torch.equal(out[0, len(rects):], blank[len(rects):])  # unused slots as wall_rectangles leaves them


def test_separate_obstructions_take_one_rectangle_each_the_one_wall_rectangles_finds():
    for grid in (20, 30):
        doc = generate_file(grid, 3, episodes=2, obstructions=range(8), snrs=("medium",))
        for s in doc["sets"]:
            for e in s["episodes"]:
                obs = [tuple(o) for o in e["obs"]]
                walls = torch.from_numpy(_union(obs, (grid, grid)))[None]
                mine = cover_rectangles(walls, 7)
                assert sorted(cover_cells(walls[0].numpy())) == sorted(obs)
                theirs = wall_rectangles(walls, 7)
                assert sorted(mine[0].tolist()) == sorted(theirs[0].tolist())


def test_touching_and_overlapping_obstructions_stay_within_the_slots():
    rng = np.random.default_rng(11)
    counts = []
    for grid in (20, 30):
        for t in range(400):
            rects = _random_obstructions(rng, grid, 7, 10 if t % 2 else grid)
            walls = _union(rects, (grid, grid))
            found = cover_cells(walls)
            assert (_union(found, walls.shape) == walls).all()
            counts.append(len(found))
    assert max(counts) <= OBSTRUCTION_SLOTS
    assert max(counts) > 7  # touching obstructions do take more than one rectangle each


def test_a_map_that_needs_more_rectangles_is_refused_saying_how_many():
    checkers = torch.zeros((1, 6, 6), dtype=torch.bool)
    checkers[0, ::2, ::2] = True
    with pytest.raises(ValueError, match=r"needs 9 rectangles .* more than the 4"):
        cover_rectangles(checkers, 4)
    with pytest.raises(ValueError, match=r"bool \[B,H,W\]"):
        cover_rectangles(checkers[0], 4)
    with pytest.raises(ValueError, match="positive integer"):
        cover_rectangles(checkers, 0)


def _posteriors(walls, rects_a, rects_b, lay, steps: int = 4):
    """The team posterior after ``steps`` readings at random free cells, started from each set of
    rectangles."""
    k, g = walls.shape[0], walls.shape[-1]
    spec = ObservationSpec("maps", 0, True)
    mems = [TeamMemory(spec, k, g, "cpu", TEAM_SENSING, posterior=True, max_walls=r.shape[1]) for r in
            (rects_a, rects_b)]
    gen = torch.Generator().manual_seed(5)
    free = (~walls).flatten(1).float()
    for t in range(steps):
        cells = torch.multinomial(free, lay["positions"].shape[1], generator=gen)
        positions = torch.stack((cells // g, cells % g), -1)
        rates = world_rates(TEAM_SENSING, 1.0, {**lay, "positions": positions})
        readings = torch.poisson(rates, generator=gen)
        for mem, rects in zip(mems, (rects_a, rects_b)):
            if t == 0:
                mem.start(walls, positions, readings, rects=rects)
            else:
                mem.record(walls, positions, readings)
    return [m.posterior() for m in mems]


def test_the_posterior_from_the_cover_is_the_one_from_the_episodes_own_rectangles():
    for grid in (20, 30):
        doc = generate_file(grid, 3, episodes=2, obstructions=range(8), snrs=("low",))
        episodes = [Episode.from_json(e, grid) for s in doc["sets"] for e in s["episodes"]]
        lay = episode_tensors(episodes, grid, 7, "cpu")
        own = torch.stack([_slots_rects(e.obstructions, 7) for e in episodes])
        mine = cover_rectangles(lay["walls"], OBSTRUCTION_SLOTS)
        a, b = _posteriors(lay["walls"], mine, own, lay)
        assert torch.allclose(a, b, rtol=0.0, atol=1e-7)
        assert torch.allclose(b, _posteriors(lay["walls"], lay["rects"], own, lay)[0], rtol=0.0, atol=1e-7)


def test_the_posterior_from_the_cover_of_touching_obstructions_is_the_one_from_their_rectangles():
    rng = np.random.default_rng(7)
    grid = 20
    episodes = []
    for _ in range(6):
        rects = _random_obstructions(rng, grid, 7, 9)
        walls = _union(rects, (grid, grid))
        free = np.argwhere(~walls)
        picks = free[rng.choice(len(free), 4, replace=False)]
        episodes.append(Episode(source=tuple(int(v) for v in picks[0]), strength=600.0, background=20,
                                starts=tuple(tuple(int(v) for v in p) for p in picks[1:]),
                                obstructions=tuple(rects), noise_seed=1))
    walls = torch.stack([torch.from_numpy(e.walls(grid)) for e in episodes])
    own = torch.stack([_slots_rects(e.obstructions, 7) for e in episodes])
    lay = {**episode_tensors(episodes, grid, 64, "cpu"), "rects": own}
    mine = cover_rectangles(walls, OBSTRUCTION_SLOTS)
    covers = [sorted(cover_cells(w.numpy())) for w in walls]
    assert any(c != sorted(e.obstructions) for c, e in zip(covers, episodes))  # other rectangles, same cells
    a, b = _posteriors(walls, mine, own, lay, steps=6)
    assert torch.allclose(a, b, rtol=0.0, atol=1e-7)
