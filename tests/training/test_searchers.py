"""The information-driven searchers (medc_training.searchers): the expected entropy and the space-aware
criterion with the strength and background marginalised match a computation by hand over every
count, the quadrature is close to the full sum where rates are large, the coordinated team splits two
agents that would otherwise buy the same reading, the two-step tree expands its best first moves, and
every searcher plays benchmark episodes through the evaluator."""

from __future__ import annotations

import math

import pytest
import torch
from medc_lab.window import play
from medc_training.controllers import SEARCHERS, controller_policy
from medc_training.envs import make_batched
from medc_training.envs.grid import action_deltas
from medc_training.envs.tl_sensing import parse_sensing
from medc_training.radbench import load_sets, play_set
from medc_training.searchers import Belief, expected_criterion, searcher_scores

#: Small rates (S 1.5 or 2.5 at the source, B 0.75 or 1.25), found only on the source's cell.
TINY = parse_sensing({"name": "realistic", "strength": [1.0, 3.0], "background": [0.5, 1.5], "levels": [2, 2],
                      "success_radius": 0.0})


def _random_log_post(levels: int, g: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand((1, levels, g * g), generator=gen).log()


def _by_hand(log_post: torch.Tensor, g: int, x: tuple[int, int], criterion: str, top: int = 80) -> float:
    """The expected criterion after a move to ``x``, summed over every count 0..top with plain Python
    arithmetic: no walls, rate S / (1 + d²) + B, found only on x's own cell."""
    s_lv, b_lv = TINY.strength_levels().tolist(), TINY.background_levels().tolist()
    levels = [(s, b) for s in s_lv for b in b_lv]  # strength-major, as the estimator keeps them
    p = torch.softmax(log_post.flatten(), 0).view(len(levels), g * g).tolist()
    cells = [(i // g, i % g) for i in range(g * g)]
    xi = x[0] * g + x[1]
    found = sum(p[lv][xi] for lv in range(len(levels)))
    q = [[0.0 if c == xi else p[lv][c] / (1 - found) for c in range(g * g)] for lv in range(len(levels))]
    total = 0.0
    for k in range(top + 1):
        joint = [[0.0] * (g * g) for _ in levels]
        for lv, (s, b) in enumerate(levels):
            for c, (r, col) in enumerate(cells):
                lam = s / (1 + (r - x[0]) ** 2 + (col - x[1]) ** 2) + b
                joint[lv][c] = q[lv][c] * math.exp(k * math.log(lam) - lam - math.lgamma(k + 1))
        pk = sum(map(sum, joint))
        if pk == 0.0:
            continue
        m = [sum(joint[lv][c] for lv in range(len(levels))) / pk for c in range(g * g)]
        h = -sum(v * math.log2(v) for v in m if v > 0)
        value = h
        if criterion == "space-aware":
            d = sum(v * max(abs(r - x[0]), abs(col - x[1])) for v, (r, col) in zip(m, cells))
            value = math.log2(d + 2 ** (h - 1) - 0.5)
        total += pk * value
    return (1 - found) * total


@pytest.mark.parametrize("criterion", ["entropy", "space-aware"])
def test_the_expected_criterion_marginalises_the_levels_exactly(criterion):
    g = 3
    log_post = _random_log_post(4, g, seed=1)
    belief = Belief.from_log_post(log_post, TINY)
    assert belief.logp.shape == (1, 4, 9)  # no level is pruned: each holds real mass
    walls = torch.zeros((1, g, g), dtype=torch.bool)
    for x in [(0, 1), (1, 1), (2, 2)]:
        got = expected_criterion(belief, torch.ones(1), torch.tensor([[x]]), walls, None, TINY, criterion,
                                 quadrature=40)
        assert float(got) == pytest.approx(_by_hand(log_post, g, x, criterion), rel=1e-4)


def test_a_level_without_mass_is_pruned_and_changes_nothing():
    g = 3
    log_post = _random_log_post(4, g, seed=2)
    log_post[0, 3] = -104.0  # the estimator's floor: no mass
    belief = Belief.from_log_post(log_post, TINY)
    assert belief.logp.shape == (1, 3, 9)
    walls = torch.zeros((1, g, g), dtype=torch.bool)
    got = expected_criterion(belief, torch.ones(1), torch.tensor([[(0, 1)]]), walls, None, TINY, "entropy",
                             quadrature=40)
    assert float(got) == pytest.approx(_by_hand(log_post, g, (0, 1), "entropy"), rel=1e-4)


def test_the_quadrature_is_close_to_the_sum_over_every_count_at_realistic_rates():
    """On the realistic preset's rates (up to ~2000; 6 x 8 levels), 6 count values against every
    count up to 2500: within 5% of the expected entropy (the quadrature overestimates it by 2-4%,
    about evenly across moves), for each move of an agent in an 8 x 8 area, and the same best move."""
    sensing = parse_sensing({"name": "realistic", "levels": [6, 8]})
    g = 8
    log_post = _random_log_post(48, g, seed=3) * 3.0  # uneven mass
    belief = Belief.from_log_post(log_post, sensing)
    walls = torch.zeros((1, g, g), dtype=torch.bool)
    cand = (torch.tensor([[3, 4]]) + action_deltas("cpu")).unsqueeze(0)  # [1,8,2]
    quick = expected_criterion(belief, torch.ones(1), cand, walls, None, sensing, "entropy")
    full = torch.cat([expected_criterion(belief, torch.ones(1), cand[:, i:i + 1], walls, None, sensing,
                                         "entropy", quadrature=2500) for i in range(8)], 1)
    assert torch.allclose(quick, full, rtol=0.05), (quick, full)
    assert int(full.argmin()) == int(quick.argmin())


def _two_agents_on_one_cell():
    """Two agents on one cell of an open 7 x 7 area; the source is in the top two rows (uniform),
    nothing else known: both would buy the same reading by moving north."""
    g = 7
    sensing = parse_sensing({"name": "realistic", "levels": [6, 8]})
    log_post = torch.full((1, 48, g * g), -104.0)
    log_post[0, :, : 2 * g] = 0.0
    positions = torch.tensor([[[4, 3], [4, 3]]])
    mask = torch.ones((1, 2, 8), dtype=torch.bool)
    walls = torch.zeros((1, g, g), dtype=torch.bool)
    return log_post, positions, mask, walls, sensing


@pytest.mark.parametrize("criterion", ["entropy", "space-aware"])
def test_the_coordinated_team_splits_agents_that_would_buy_the_same_reading(criterion):
    log_post, positions, mask, walls, sensing = _two_agents_on_one_cell()
    alone = searcher_scores(log_post, positions, mask, walls, sensing, criterion=criterion)
    team = searcher_scores(log_post, positions, mask, walls, sensing, criterion=criterion, coordinated=True)
    independent = alone[0].argmax(-1).tolist()
    assert independent[0] == independent[1]  # each alone: the same move
    assert torch.equal(team[0, 0], alone[0, 0])  # agent 0 chooses first, as if alone
    chosen = team[0].argmax(-1).tolist()
    assert chosen[0] == independent[0] and chosen[1] != chosen[0]
    # Agent 1's value of following agent 0 is what it expects after agent 0's reading: worth more
    # than elsewhere alone, worth less with it.
    deltas = action_deltas("cpu").tolist()
    assert deltas[chosen[0]][0] < 0 and deltas[chosen[1]][0] <= 0  # both still head for the top rows


def test_two_step_infotaxis_expands_the_best_first_moves_and_looks_further():
    log_post, positions, mask, walls, sensing = _two_agents_on_one_cell()
    one = searcher_scores(log_post, positions[:, :1], mask[:, :1], walls, sensing)
    two = searcher_scores(log_post, positions[:, :1], mask[:, :1], walls, sensing, depth=2)
    # Two moves teach at least what one does: the expanded moves' expected entropy is lower.
    expanded = (-two[0, 0]) < (-one[0, 0]) - 1e-6
    assert 1 <= int(expanded.sum()) <= 3
    assert bool(torch.isfinite(two).all())
    with pytest.raises(ValueError, match="depth"):
        searcher_scores(log_post, positions, mask, walls, sensing, depth=2, coordinated=True)


@pytest.mark.parametrize("name", sorted(SEARCHERS))
def test_each_searcher_plays_benchmark_episodes_to_their_end(name):
    agents = 3 if name.startswith("team-") else 1
    (bench_set,) = load_sets(grid=20, agents=agents, obstructions=[2], snrs=["high"])
    results = play_set(bench_set, name, episodes=2)
    assert [r.index for r in results] == [0, 1] and all(1 <= r.length <= 120 for r in results)
    assert any(r.success for r in results)


def test_a_searcher_is_a_policy_of_the_batched_core():
    env = make_batched("target_localization", num_envs=4, seed=3, agents=2, walls=1, grid=9, max_steps=20,
                       sensing="realistic", posterior=True)
    policy = controller_policy("team-space-aware", env)
    first = play(env, policy, episodes=4, seed=5)
    assert play(env, policy, episodes=4, seed=5) == first  # deterministic
