"""The realistic sensing preset: readings by its stated formula, line of sight through walls, the
team's posterior with unknown strength and background against one computed by hand."""

from __future__ import annotations

import math

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.tl_observation import LOG_FLOOR, SourceEstimator
from medc_training.envs.tl_sensing import (
    SENSING_PRESETS,
    geometric_factor,
    parse_sensing,
    realistic_rates,
    wall_rectangles,
)

REALISTIC = SENSING_PRESETS["realistic"]


def rate(strength, background, sensor, source, walls=None):
    g = 9 if walls is None else walls.shape[-1]
    walls = torch.zeros((1, g, g), dtype=torch.bool) if walls is None else walls.unsqueeze(0)
    return float(realistic_rates(REALISTIC, torch.tensor([[sensor]]), torch.tensor([source]), walls,
                                 torch.tensor([strength]), torch.tensor([background]))[0, 0])


def test_open_field_rate_is_strength_over_one_plus_distance_squared_plus_background() -> None:
    assert rate(800.0, 20.0, (4, 4), (4, 4)) == pytest.approx(800.0 + 20.0)
    assert rate(800.0, 20.0, (4, 5), (4, 4)) == pytest.approx(800.0 / 2 + 20.0)
    assert rate(800.0, 20.0, (1, 0), (4, 4)) == pytest.approx(800.0 / (1 + 9 + 16) + 20.0)
    assert rate(1000.0, 35.0, (0, 0), (8, 8)) == pytest.approx(1000.0 / 129 + 35.0)


def test_a_wall_on_the_line_of_sight_leaves_only_the_background() -> None:
    walls = torch.zeros((9, 9), dtype=torch.bool)
    walls[2:7, 4] = True  # a vertical segment, column 4, rows 2..6
    assert rate(800.0, 20.0, (4, 1), (4, 7), walls) == 20.0  # straight through it
    assert rate(800.0, 20.0, (0, 1), (0, 7), walls) == pytest.approx(800.0 / 37 + 20.0)  # above it
    # The line from (1,3) to (1,5) passes above the wall's top edge (row 1.5): in sight.
    assert rate(800.0, 20.0, (1, 3), (1, 5), walls) == pytest.approx(800.0 / 5 + 20.0)
    # (1,1) -> (7,7) crosses column 4 at row 4: blocked. (0,2) -> (2,6) crosses column 3.5..4.5
    # at rows 0.75..1.25: above the top edge (1.5), in sight.
    assert rate(800.0, 20.0, (1, 1), (7, 7), walls) == 20.0
    assert rate(800.0, 20.0, (0, 2), (2, 6), walls) == pytest.approx(800.0 / 21 + 20.0)
    # A partial attenuation halves the rate once per wall crossed.
    half = parse_sensing({"name": "realistic", "attenuation": 0.5})
    f = geometric_factor(half, torch.tensor([[[4, 1]]]), torch.tensor([[4, 7]]), walls.unsqueeze(0))
    assert float(f[0, 0, 0]) == pytest.approx(0.5 / 37)


def test_wall_rectangles_recover_every_segment() -> None:
    walls = torch.zeros((2, 10, 10), dtype=torch.bool)
    walls[0, 1, 2:6] = True
    walls[0, 5:9, 8] = True
    walls[1, 3:5, 0] = True
    rects = wall_rectangles(walls, 3)
    got0 = sorted(tuple(r) for r in rects[0].tolist() if r[2] > r[0])
    assert got0 == [(0.5, 1.5, 1.5, 5.5), (4.5, 7.5, 8.5, 8.5)]
    got1 = [tuple(r) for r in rects[1].tolist() if r[2] > r[0]]
    assert got1 == [(2.5, -0.5, 4.5, 0.5)]
    # More slots than a small map has cells: the segments, then empty slots.
    tiny = torch.zeros((1, 2, 2), dtype=torch.bool)
    tiny[0, 0, :] = True
    roomy = wall_rectangles(tiny, 6)
    assert roomy.shape == (1, 6, 4)
    assert [tuple(r) for r in roomy[0].tolist() if r[2] > r[0]] == [(-0.5, -0.5, 0.5, 1.5)]


def test_the_core_draws_strength_and_background_per_episode_and_always_counts_poisson() -> None:
    env = make_batched("target_localization", num_envs=64, seed=3, grid=12, walls=1, max_steps=20,
                       sensing="realistic")
    env.reset()
    assert env.noise
    s, b = env.strength, env.background
    assert float(s.min()) >= 200.0 and float(s.max()) <= 2000.0 and float(s.std()) > 100.0
    assert float(b.min()) >= 10.0 and float(b.max()) <= 50.0
    assert torch.equal(env.readings, env.readings.round())  # counts
    with pytest.raises(ValueError, match="always counts Poisson noise"):
        make_batched("target_localization", grid=12, sensing="realistic", noise=False)
    assert env.attributes["sensing"] == "realistic"
    assert "sensing" not in make_batched("target_localization", grid=12).attributes


def test_success_within_the_radius() -> None:
    env = make_batched("target_localization", num_envs=1, seed=0, grid=9, walls=0, max_steps=50,
                       sensing="realistic", observation="maps")
    env.reset()
    target = env.state(0).target
    # Walk agent 0 towards the source with the oracle; the episode ends one cell away (radius 1.1).
    for _ in range(20):
        out = env.step(env.oracle_action_scores().argmax(-1))
        if bool(out.done[0]):
            break
    assert bool(out.terminated[0])
    final = env.state(0)  # already the next episode; the length says when it ended
    assert int(out.episode_length[0]) >= 1 and final.step == 0 and target is not None


def in_sight(a, b, walls_cells) -> bool:
    """No point of the segment a-b (2,000 samples) lies strictly inside a wall cell's square."""
    for k in range(1, 2000):
        t = k / 2000
        r, c = a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])
        if any(abs(r - wr) < 0.5 and abs(c - wc) < 0.5 for wr, wc in walls_cells):
            return False
    return True


def hand_posterior(grid, walls_cells, sensing, readings):
    """The posterior over source cells by explicit sums: uniform prior over free cells and over
    the (strength, background) levels, Poisson likelihood, walls blocking the line of sight,
    visited cells ruled out."""
    s_levels = sensing.strength_levels().tolist()
    b_levels = sensing.background_levels().tolist()
    weights = {}
    visited = {pos for pos, _ in readings}
    for r in range(grid):
        for c in range(grid):
            if (r, c) in walls_cells or any(math.dist((r, c), v) <= sensing.success_radius for v in visited):
                continue
            total = 0.0
            for s in s_levels:
                for b in b_levels:
                    loglik = 0.0
                    for (pr, pc), count in readings:
                        seen = in_sight((pr, pc), (r, c), walls_cells)
                        lam = seen * s / (1 + (pr - r) ** 2 + (pc - c) ** 2) + b
                        loglik += count * math.log(lam) - lam
                    total += math.exp(loglik)
            weights[(r, c)] = total
    z = sum(weights.values())
    return {cell: w / z for cell, w in weights.items()}


def test_posterior_with_unknown_strength_and_background_equals_the_hand_computed_one() -> None:
    grid = 6
    sensing = parse_sensing({"name": "realistic", "levels": [3, 2]})
    est = SourceEstimator(grid, "cpu", sensing)
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    walls[0, 3, 3] = True
    log_post = est.prior(walls)
    assert log_post.shape == (1, 6, grid * grid)
    readings = [((0, 0), 31.0), ((5, 5), 12.0), ((0, 5), 25.0), ((2, 1), 60.0)]
    # One reading per call, as a team of one.
    for (pr, pc), count in readings:
        est.update(log_post, walls, torch.tensor([[[pr, pc]]]), torch.tensor([[count]]))
    got = est.posterior(log_post)[0].view(grid, grid)
    want = hand_posterior(grid, {(3, 3)}, sensing, readings)
    for r in range(grid):
        for c in range(grid):
            expected = want.get((r, c), 0.0)
            assert float(got[r, c]) == pytest.approx(expected, rel=2e-3, abs=1e-6), (r, c)
    assert float(got[3, 3]) == 0.0 and float(got[0, 0]) == 0.0  # a wall; a visited cell
    assert float(log_post.max()) == 0.0 and float(log_post.min()) >= LOG_FLOOR


def test_expected_moves_is_the_chebyshev_expectation() -> None:
    grid = 7
    est = SourceEstimator(grid, "cpu")
    log_post = torch.full((1, grid * grid), LOG_FLOOR)
    log_post[0, 1 * grid + 5] = math.log(0.4)
    log_post[0, 6 * grid + 0] = math.log(0.6)
    e = est.expected_moves(log_post)[0].view(grid, grid)
    for r in range(grid):
        for c in range(grid):
            want = 0.4 * max(abs(r - 1), abs(c - 5)) + 0.6 * max(abs(r - 6), abs(c - 0))
            assert float(e[r, c]) == pytest.approx(want, abs=1e-5)


@pytest.mark.parametrize("block_bytes", [1, 200_000, 1 << 30])
def test_the_posterior_over_levels_is_the_same_in_blocks_of_any_size(monkeypatch, block_bytes) -> None:
    """The update and the marginal run a block of episodes at a time (BLOCK_BYTES): one episode per
    block, several, or the whole batch give the same bits, wall and ruled-out cells included."""
    import medc_training.envs.tl_observation as tlo

    def play(block: int) -> list[torch.Tensor]:
        monkeypatch.setattr(tlo, "BLOCK_BYTES", block)
        env = make_batched("target_localization", num_envs=11, seed=5, agents=3, walls=2, grid=16,
                           max_steps=30, sensing="realistic", observation="ego6+estimate")
        gen = torch.Generator().manual_seed(2)
        _, mask = env.reset()
        seen = []
        for _ in range(20):
            b, n, a = mask.shape
            step = env.step(torch.multinomial(mask.view(-1, a).float(), 1, generator=gen).view(b, n))
            mask = step.mask
            seen += [env.memory.log_post.clone(), env.memory.posterior(), step.obs]
        return seen

    reference = play(1 << 30)
    assert SourceEstimator(16, "cpu", "realistic").block(11) == 11
    with_blocks = play(block_bytes)
    assert all(torch.equal(x, y) for x, y in zip(reference, with_blocks, strict=True))
