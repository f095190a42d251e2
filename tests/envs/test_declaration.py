"""The team's declaration that it has localised the source (medc_training.envs.tl_estimate), the core
options behind a declaration-ended episode (end_on_find, end_episode, the estimator's rule_out) and the
declaration study (medc_training.declaration_eval)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from medc_training.envs import make_batched
from medc_training.envs.tl_estimate import (
    DEFAULT_THRESHOLD,
    declare,
    map_cells,
    mass_within,
    mean_and_covariance,
)
from medc_training.envs.tl_observation import SourceEstimator

#: (drow, dcol) -> action (N, NE, E, SE, S, SW, W, NW).
MOVES = {(-1, 0): 0, (-1, 1): 1, (0, 1): 2, (1, 1): 3, (1, 0): 4, (1, -1): 5, (0, -1): 6, (-1, -1): 7}
TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"


def posterior(grid: int, cells: dict[tuple[int, int], float]) -> torch.Tensor:
    p = torch.zeros(1, grid * grid)
    for (r, c), v in cells.items():
        p[0, r * grid + c] = v
    return p


def test_a_sure_posterior_declares_its_cell():
    v = declare(posterior(5, {(1, 3): 1.0}), 5, radius=0.0)
    assert bool(v.declared[0]) and v.cell[0].tolist() == [1, 3] and float(v.mass[0]) == pytest.approx(1.0)


def test_the_radius_decides_how_much_mass_counts():
    p = posterior(7, {(3, 3): 0.6, (3, 4): 0.3, (4, 4): 0.1})
    assert not bool(declare(p, 7, radius=0.0).declared[0])  # 0.6 on the MAP cell alone
    v = declare(p, 7, radius=1.1)  # the cell and its 4 edge neighbours: 0.9, not the diagonal
    assert float(v.mass[0]) == pytest.approx(0.9) and not bool(v.declared[0])
    assert bool(declare(p, 7, radius=1.1, threshold=0.9).declared[0])
    assert bool(declare(p, 7, radius=1.5).declared[0])  # the diagonal (sqrt 2) too: mass 1
    assert float(mass_within(p, 7, torch.tensor([[4, 4]]), 1.0)) == pytest.approx(0.4)


def test_threshold_and_radius_are_checked():
    p = posterior(5, {(0, 0): 1.0})
    for radius, threshold in ((-1.0, 0.5), (float("inf"), 0.5), (0.0, 0.0), (0.0, 1.5)):
        with pytest.raises(ValueError, match=r"radius|threshold"):
            declare(p, 5, radius, threshold)
    with pytest.raises(ValueError, match=r"\[B, 36\]"):
        declare(p, 6, 0.0)


def test_batched_verdicts_are_each_episode_s_own():
    p = torch.cat([posterior(5, {(2, 2): 1.0}), posterior(5, {(0, 0): 0.5, (4, 4): 0.5})])
    v = declare(p, 5, 0.0, DEFAULT_THRESHOLD)
    assert v.declared.tolist() == [True, False]
    assert map_cells(p, 5).tolist() == [[2, 2], [0, 0]]  # a tie takes the lowest index


def test_mean_and_covariance_of_the_posterior():
    p = posterior(5, {(1, 1): 0.5, (1, 3): 0.5})  # same row, columns 1 and 3
    mean, cov = mean_and_covariance(p, 5)
    assert mean[0].tolist() == pytest.approx([1.0, 2.0])
    assert cov[0].flatten().tolist() == pytest.approx([0.0, 0.0, 0.0, 1.0])


def test_rule_out_off_keeps_the_cells_the_team_stood_on():
    walls = torch.zeros(1, 5, 5, dtype=torch.bool)
    positions = torch.tensor([[[2, 2]]])
    reading = torch.tensor([[1001.0]])  # the source's own rate (paper-simple): it is right here
    for rule_out, expected in ((True, 0.0), (False, 1.0)):
        est = SourceEstimator(5, "cpu", rule_out=rule_out)
        log_post = est.prior(walls)
        est.update(log_post, walls, positions, reading)
        assert float(est.posterior(log_post)[0, 2 * 5 + 2]) == pytest.approx(expected, abs=1e-6)


def test_end_on_find_false_lets_the_caller_end_episodes():
    env = make_batched("target_localization", num_envs=1, seed=5, agents=1, walls=0, grid=5, max_steps=20,
                       end_on_find=False, posterior=True)
    env.reset()
    s = env.state(0)
    # Walk the agent onto the source: the episode goes on, no success, and the posterior keeps the cell.
    for _ in range(8):
        (r, c), (tr, tc) = env.state(0).positions[0], s.target
        if (r, c) == (tr, tc):
            break
        dr, dc = (tr > r) - (tr < r), (tc > c) - (tc < c)
        out = env.step(torch.tensor([[MOVES[(dr, dc)]]]))
        assert not bool(out.terminated[0] | out.success[0])
    assert env.state(0).positions[0] == s.target
    assert bool(declare(env.memory.posterior(), 5, 0.0).declared[0])
    steps = env.state(0).step
    assert steps > 0
    env.end_episode(0)
    after = env.state(0)
    assert after.step == 0 and float(env.memory.visit_map.sum()) == 1.0  # a fresh episode and memory


def test_end_episode_starts_the_episode_the_core_would_have():
    a = make_batched("target_localization", num_envs=1, seed=9, agents=2, walls=1, grid=8, max_steps=1)
    b = make_batched("target_localization", num_envs=1, seed=9, agents=2, walls=1, grid=8, max_steps=1)
    a.reset(), b.reset()
    a.end_episode(0)
    b.step(torch.zeros(1, 2, dtype=torch.long))  # max_steps = 1: truncated, auto-reset
    assert a.state(0).target == b.state(0).target and a.state(0).positions == b.state(0).positions


def test_declaration_study_on_the_shipped_team():
    """The shipped team (paper-simple, noise-free) declares the right cell in every episode."""
    from medc_training.bundle import load_bundle
    from medc_training.declaration_eval import declaration_episodes, summarize

    bundle = load_bundle(TEAM)
    attrs = dict(bundle.manifest["environment"], observation=bundle.observation, posterior=True)
    for end_on_find in (True, False):
        env = make_batched("target_localization", num_envs=8, seed=1, end_on_find=end_on_find, **attrs)
        rows = declaration_episodes(env, bundle, episodes=16, seed=1)
        s = summarize(rows)
        assert s["episodes"] == 16 and s["declared"] == s["declared_correct"] >= 12, s
        if not end_on_find:
            assert s["declared"] == 16 and s["found_first"] == 0
        assert all(row["length"] <= 50 for row in rows)
