"""The fused estimator path against the reference path it replaced: the exact line-of-sight test equals
the slab method's decisions, posteriors and observations agree within the stated tolerance on hand cases
and over 100-step traces of both presets, and the fused path keeps every property the reference has
(batch-size independence, exact zeros on ruled-out cells, a posterior over levels read as [B, L, G²])."""

from __future__ import annotations

import math

import pytest
import torch
from env_scenarios import estimator_trace
from medc_training.envs import make_batched, tl_native
from medc_training.envs import tl_observation as tlo
from medc_training.envs.target_localization import max_walls
from medc_training.envs.tl_observation import (
    EXP_FLOOR,
    LOG_FLOOR,
    SourceEstimator,
    TeamMemory,
    estimator_path,
)
from medc_training.envs.tl_sensing import (
    _blocked,
    _blocked_exact,
    _pair_tables,
    parse_sensing,
    sight_lines,
    wall_rectangles,
)

#: The stated tolerance between the fused and the reference path (docs/environments.md, "Speed"):
#: posterior probabilities and observation values, max abs difference.
POSTERIOR_TOLERANCE = 1e-3
OBSERVATION_TOLERANCE = 1e-4


def _every_sensor(walls: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    g = walls.shape[-1]
    return torch.stack((cells // g, cells % g), -1).unsqueeze(0).expand(walls.shape[0], -1, -1).contiguous()


@pytest.mark.parametrize("grid", [6, 13, 20])
def test_the_exact_sight_test_makes_the_slab_methods_decisions_on_every_pair(grid) -> None:
    env = make_batched("target_localization", num_envs=12, seed=grid, agents=1, walls=max_walls(grid),
                       grid=grid, sensing="realistic")
    env.reset()
    walls = env.walls
    rects = wall_rectangles(walls)
    inv = _pair_tables(grid, grid, walls.device)[0]
    for cells in torch.arange(grid * grid).split(100):
        positions = _every_sensor(walls, cells)
        free = ~walls.reshape(len(walls), -1)[:, cells].unsqueeze(-1)  # sensors stand on free cells
        cell = positions[..., 0] * grid + positions[..., 1]
        for count in (False, True):
            want = _blocked(positions, inv[cell], rects, count=count)
            got = _blocked_exact(positions, rects, grid, grid, count=count)
            keep = free.float()
            assert torch.equal(got.float() * keep, want.float() * keep)
        reference = sight_lines(env.sensing, positions, walls, rects)
        fused = sight_lines(env.sensing, positions, walls, rects, fused=True)
        assert torch.equal(reference[0][free.squeeze(-1)], fused[0][free.squeeze(-1)])
        assert torch.equal(reference[1] * free, fused[1] * free)


def test_the_exact_sight_test_on_hand_cases() -> None:
    """A corner touch and a run along a side are no crossing; through the middle is."""
    rects = torch.tensor([[[1.5, 3.5, 2.5, 6.5]]])  # a horizontal wall: row 2, columns 4..6
    cases = {  # (sensor, source): crossed
        ((2, 2), (2, 8)): True,  # along the wall's row, through it
        ((1, 2), (1, 8)): False,  # one row above: runs along no side (row 1 < 1.5)
        ((0, 2), (4, 8)): True,  # diagonal through it
        ((0, 1), (3, 4)): False,  # slope 1 through the corner (1.5, 3.5): a touch
        ((0, 5), (4, 5)): True,  # straight down through it
        ((0, 8), (4, 8)): False,  # beside it
    }
    for (p, s), crossed in cases.items():
        positions = torch.tensor([[p]])
        got = _blocked_exact(positions, rects, 10, 10, count=False)[0, 0, s[0] * 10 + s[1]]
        inv = _pair_tables(10, 10, positions.device)[0][torch.tensor([[p[0] * 10 + p[1]]])]
        want = _blocked(positions, inv, rects, count=False)[0, 0, s[0] * 10 + s[1]]
        assert bool(got) == bool(want) == crossed, (p, s)


def _hand_posterior(grid: int, walls: set, sensing, readings) -> torch.Tensor:
    """float64 posterior over cells, strength and background marginalised (open field)."""
    est = SourceEstimator(grid, "cpu", sensing)
    s_lv, b_lv = (x.double().tolist() for x in est.sensing.level_values())
    out = torch.zeros(grid * grid, dtype=torch.float64)
    for cell in range(grid * grid):
        r, c = divmod(cell, grid)
        if (r, c) in walls or any((pr, pc) == (r, c) for (pr, pc), _ in readings):
            continue
        for strength, background in zip(s_lv, b_lv, strict=True):
            loglik = 0.0
            for (pr, pc), count in readings:
                lam = strength / (1.0 + (pr - r) ** 2 + (pc - c) ** 2) + background
                loglik += count * math.log(lam) - lam
            out[cell] += math.exp(loglik - 50.0)
    return out / out.sum()


@pytest.mark.parametrize("path", tlo.ESTIMATOR_PATHS)
def test_both_paths_equal_the_hand_computed_posterior(path) -> None:
    grid = 7
    sensing = parse_sensing({"name": "realistic", "levels": [4, 3]})
    readings = [((0, 0), 40.0), ((6, 6), 14.0), ((0, 6), 22.0), ((3, 1), 75.0), ((5, 2), 30.0)]
    est = SourceEstimator(grid, "cpu", sensing, path=path)
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    log_post = est.prior(walls)
    assert est.cells_major(log_post) == (path == "fused")
    post = torch.empty((1, grid * grid))
    for (pr, pc), count in readings:
        filled = est.update(log_post, walls, torch.tensor([[[pr, pc]]]), torch.tensor([[count]]),
                            posterior_out=post)
        assert filled == (path == "fused")
    got = est.posterior(log_post)[0].double()
    want = _hand_posterior(grid, set(), sensing, readings)
    assert float((got - want).abs().max()) < 1e-5
    assert all(float(got[r * grid + c]) == 0.0 for (r, c), _ in readings)  # ruled out: exactly 0
    if path == "fused":
        assert torch.equal(post[0], est.posterior(log_post)[0])  # written in the update's pass


@pytest.mark.parametrize(("sensing", "grid"), [("realistic", 20), ("realistic", 12), ("paper-simple", 13)])
def test_a_100_step_trace_agrees_within_the_stated_tolerance(sensing, grid) -> None:
    fused, reference = estimator_trace(sensing, grid, "fused"), estimator_trace(sensing, grid, "reference")
    d_obs = max(float((f[0] - r[0]).abs().max()) for f, r in zip(fused, reference, strict=True))
    d_post = max(float((f[1] - r[1]).abs().max()) for f, r in zip(fused, reference, strict=True))
    assert all(torch.equal(f[2], r[2]) for f, r in zip(fused, reference, strict=True))  # the same episodes
    assert d_post <= POSTERIOR_TOLERANCE and d_obs <= OBSERVATION_TOLERANCE
    # A zero in one path is at most a dead cell's mass in the other.
    for f, r in zip(fused, reference, strict=True):
        assert bool((r[1][f[1] == 0] < 1e-30).all()) and bool((f[1][r[1] == 0] < 1e-30).all())
    if sensing == "paper-simple" and not tl_native.usable():  # one level, no kernel: the same code
        assert d_post == 0.0 and d_obs == 0.0


def test_the_fused_posterior_is_the_same_at_any_batch_size() -> None:
    """One episode's posterior does not depend on how many share its batch (the ROS node runs B = 1)."""
    grid, batch = 14, 6
    env = make_batched("target_localization", num_envs=batch, seed=3, agents=3, walls=2, grid=grid,
                       sensing="realistic", posterior=True)
    env.reset()
    walls, rects = env.walls, env.memory.rects
    gen = torch.Generator().manual_seed(0)
    together = TeamMemory("ego6+estimate", batch, grid, "cpu", "realistic", max_walls=2)
    alone = [TeamMemory("ego6+estimate", 1, grid, "cpu", "realistic", max_walls=2) for _ in range(batch)]
    for step in range(12):
        positions = torch.randint(0, grid, (batch, 3, 2), generator=gen)
        readings = torch.poisson(torch.full((batch, 3), 30.0), generator=gen)
        if step == 0:
            together.start(walls, positions, readings, rects=rects)
            for b, mem in enumerate(alone):
                mem.start(walls[b:b + 1], positions[b:b + 1], readings[b:b + 1], rects=rects[b:b + 1])
        else:
            together.record(walls, positions, readings)
            for b, mem in enumerate(alone):
                mem.record(walls[b:b + 1], positions[b:b + 1], readings[b:b + 1])
        for b, mem in enumerate(alone):
            assert torch.equal(together.log_post[b], mem.log_post[0])
            assert torch.equal(together.posterior()[b], mem.posterior()[0])


def test_the_fused_memory_reads_as_levels_by_cells_and_keeps_its_posterior_only_while_valid() -> None:
    with estimator_path("fused"):
        env = make_batched("target_localization", num_envs=5, seed=1, agents=3, walls=2, grid=10,
                           sensing="realistic", posterior=True)
    env.reset()
    mem = env.memory
    levels = mem.estimator.levels
    assert mem.log_post.shape == (5, levels, 100) and mem.estimator.cells_major(mem.log_post)
    assert float(mem.log_post.amax((1, 2)).abs().max()) == 0.0 and float(mem.log_post.min()) >= LOG_FLOOR
    kept = mem.posterior()
    assert torch.equal(kept, mem.estimator.posterior(mem.log_post))
    kept.zero_()  # a caller's copy: the memory's own stays
    assert float(mem.posterior().sum(1).sub(1).abs().max()) < 1e-5
    mem.log_post[0, 0, 0] = 0.0  # changed behind the memory's back: recomputed, never stale
    assert torch.equal(mem.posterior(), mem.estimator.posterior(mem.log_post))
    # The reference reads the same tensor (a view of cells-major memory) as well.
    reference = SourceEstimator(10, "cpu", "realistic", path="reference")
    assert float((reference.posterior(mem.log_post) - mem.posterior()).abs().max()) < 1e-6
    dead = mem.log_post.amax(1) <= EXP_FLOOR
    assert bool((mem.posterior()[dead] == 0).all())


def test_the_path_is_one_of_two_and_the_old_one_stays_selectable() -> None:
    assert tlo.ESTIMATOR_PATHS == ("fused", "reference")
    with estimator_path("reference"):
        assert SourceEstimator(8, "cpu", "realistic").path == "reference"
        assert not SourceEstimator(8, "cpu", "realistic").fused
    assert SourceEstimator(8, "cpu", "realistic", path="fused").fused
    assert not SourceEstimator(8, "cpu", "paper-simple", path="fused").fused  # one level: nothing to fuse
    with pytest.raises(ValueError, match="estimator path must be one of"), estimator_path("fast"):
        pass
    with pytest.raises(ValueError, match="estimator path must be one of"):
        SourceEstimator(8, "cpu", path="fast")
