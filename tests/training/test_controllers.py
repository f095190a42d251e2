"""The classical controllers (medc_training.controllers): each plays through the evaluator's play loop
and beats random moves, greedy and gradient move where a hand computation says, infotaxis prefers
the informative move, and a core without a posterior is refused with a clear message."""

from __future__ import annotations

import math

import pytest
import torch
from medc_lab.window import play
from medc_training.cli.play_controllers import main
from medc_training.controllers import (
    CONTROLLERS,
    controller_policy,
    expected_chebyshev,
    first_episodes,
    gradient_scores,
    greedy_scores,
    infotaxis_scores,
)
from medc_training.envs import make_batched
from medc_training.envs.grid import ACTION_NAMES, action_deltas, move_mask, pad_blocked
from medc_training.envs.tl_sensing import SENSING_PRESETS, update_memory

SMALL = dict(agents=2, walls=1, grid=9, max_steps=30)


def _env(sensing: str, **extra):
    return make_batched("target_localization", num_envs=16, seed=3, sensing=sensing, **{**SMALL, **extra})


@pytest.fixture(scope="module")
def random_play() -> dict[str, dict]:
    # The same episodes as the controllers' (the posterior draws nothing), without its cost.
    return {s: first_episodes(_env(s, observation="maps"), None, seed=11)
            for s in ("realistic", "paper-simple")}


@pytest.mark.parametrize("sensing", ["realistic", "paper-simple"])
@pytest.mark.parametrize("name", CONTROLLERS)
def test_each_controller_beats_random_moves_on_the_same_episodes(name, sensing, random_play):
    env = _env(sensing, posterior=True)
    got = first_episodes(env, controller_policy(name, env), seed=11)
    rnd = random_play[sensing]
    assert got["episodes"] == rnd["episodes"] == 16
    assert got["success_rate"] >= rnd["success_rate"]
    assert got["episode_length"] < rnd["episode_length"]
    assert got["decisions_per_s"] > 0


@pytest.mark.parametrize("name", CONTROLLERS)
def test_a_controller_plays_through_play_like_a_bundle(name):
    """A controller is an ordinary Policy: play(episodes=...) and play(steps=...) take it, it never
    picks a masked move, and the same seed replays the same episodes."""
    env = _env("realistic")  # the default observation shows the estimate, so the core keeps a posterior
    policy = controller_policy(name, env)
    first = play(env, policy, episodes=8, seed=5)
    assert len(first.lengths) == 8
    assert play(env, policy, episodes=8, seed=5) == first
    # its scores are -inf exactly on the masked moves, and every move it chose was allowed
    obs, mask = env.reset(seed=9)
    for _ in range(5):
        logits = policy(obs.flatten(0, 1), mask.flatten(0, 1)).view(mask.shape)
        assert torch.isneginf(logits[~mask]).all() and torch.isfinite(logits[mask]).all()
        actions = logits.argmax(-1)
        assert mask.gather(2, actions.unsqueeze(2)).all()
        out = env.step(actions)
        obs, mask = out.obs, out.mask


def test_greedy_moves_to_the_hand_chosen_neighbour():
    g = 7
    post = torch.zeros(1, g * g)
    post[0, 1 * g + 5], post[0, 5 * g + 5] = 0.7, 0.3
    pos = torch.tensor([[[3, 3]]])
    mask = torch.ones(1, 1, 8, dtype=torch.bool)
    # E(2,4) = 0.7*1 + 0.3*3 = 1.6 < E(3,4) = 2.0 < E(2,3) = 2.3: north-east.
    e = expected_chebyshev(post, g).view(g, g)
    assert e[2, 4].item() == pytest.approx(1.6) and e[3, 4].item() == pytest.approx(2.0)
    scores = greedy_scores(post, pos, mask)
    assert ACTION_NAMES[int(scores.argmax())] == ACTION_NAMES[1] and int(scores.argmax()) == 1
    assert scores[0, 0, 2].item() == pytest.approx(-2.0)
    # A tie (E = 2 at NE, E and SE) goes to the least visited cell, then the lowest action index.
    post[0, 1 * g + 5], post[0, 5 * g + 5] = 0.5, 0.5
    visits = torch.zeros(1, g, g)
    visits[0, 2, 4], visits[0, 3, 4], visits[0, 4, 4] = 2.0, 1.0, 1.0
    assert int(greedy_scores(post, pos, mask, visits).argmax()) == 2  # E
    mask[0, 0, 2] = False
    scores = greedy_scores(post, pos, mask, visits)
    assert int(scores.argmax()) == 3 and torch.isneginf(scores[0, 0, 2])  # SE


@pytest.mark.parametrize("sensing", ["paper-simple", "realistic"])
def test_infotaxis_prefers_the_informative_move(sensing):
    """Two equally likely source cells, (0,0) and (0,4); the agent at (3,2). Moving north keeps it
    equidistant (the reading cannot tell them apart: expected entropy ln 2), which is what greedy
    picks (it is the closest to both); north-east and north-west tell them apart."""
    g = 5
    model = SENSING_PRESETS[sensing]
    post = torch.zeros(1, g * g)
    post[0, 0], post[0, 4] = 0.5, 0.5
    pos = torch.tensor([[[3, 2]]])
    walls = torch.zeros(1, g, g, dtype=torch.bool)
    mask = move_mask(pos, pad_blocked(walls), action_deltas("cpu"))
    scores = infotaxis_scores(post, pos, mask, walls, model)
    assert -scores[0, 0, 0].item() == pytest.approx(math.log(2), abs=1e-3)  # N: nothing learned
    assert scores[0, 0, 1] > scores[0, 0, 0] + 0.5 and scores[0, 0, 7] > scores[0, 0, 0] + 0.5
    assert int(scores.argmax()) == 1  # NE and NW tie; the lower action index
    assert int(greedy_scores(post, pos, mask).argmax()) == 0


def test_infotaxis_counts_the_chance_of_finding_the_source():
    """A move onto a likely source cell ends the search with that probability (entropy 0)."""
    g = 5
    post = torch.zeros(1, g * g)
    post[0, 1 * g + 2], post[0, 4 * g + 4] = 0.9, 0.1
    pos = torch.tensor([[[2, 2]]])
    walls = torch.zeros(1, g, g, dtype=torch.bool)
    mask = move_mask(pos, pad_blocked(walls), action_deltas("cpu"))
    scores = infotaxis_scores(post, pos, mask, walls, SENSING_PRESETS["paper-simple"])
    assert int(scores.argmax()) == 0  # N, onto (1,2)


def test_gradient_climbs_a_plane_and_explores_where_flat():
    g = 7
    pos = torch.tensor([[[3, 3]]])
    mask = torch.ones(1, 1, 8, dtype=torch.bool)
    cells = torch.tensor([[[r, c] for r in range(2, 5) for c in range(2, 5)]])
    model = SENSING_PRESETS["paper-simple"]
    for slope, want in ((20.0, 2), (-20.0, 6)):  # rising to the east: E; to the west: W
        reading, visits = torch.zeros(1, g, g), torch.zeros(1, g, g)
        update_memory(reading, visits, cells, 100.0 + slope * cells[..., 1].float(), model.max_rate)
        assert int(gradient_scores(reading, visits, pos, mask, model).argmax()) == want
    # Flat readings: the least visited neighbour (all the window's were visited once; add one).
    reading, visits = torch.zeros(1, g, g), torch.zeros(1, g, g)
    update_memory(reading, visits, cells, torch.full((1, 9), 50.0), model.max_rate)
    visits[0, 2, 2] = visits[0, 2, 3] = visits[0, 2, 4] = visits[0, 3, 4] = 2.0
    assert int(gradient_scores(reading, visits, pos, mask, model).argmax()) == 3  # SE, first of SE/S/SW/W
    # With Poisson counts, a slope within the noise is flat too.
    noisy = SENSING_PRESETS["realistic"]
    reading, visits = torch.zeros(1, g, g), torch.zeros(1, g, g)
    update_memory(reading, visits, cells, 100.0 + 0.5 * cells[..., 1].float(), noisy.max_rate)
    visits[0, 3, 4] = 5.0
    assert int(gradient_scores(reading, visits, pos, mask, noisy, background=30.0).argmax()) != 2


@pytest.mark.parametrize("name", ["greedy", "infotaxis"])
def test_a_core_without_posterior_is_refused(name):
    env = _env("realistic", observation="maps")
    with pytest.raises(ValueError, match="posterior=True"):
        controller_policy(name, env)
    controller_policy("gradient", env)  # needs none
    with pytest.raises(ValueError, match="unknown controller"):
        controller_policy("simplex", env)
    with pytest.raises(ValueError, match="target localization"):
        controller_policy("greedy", make_batched("maze_cleaning", num_envs=2, seed=0))


def test_the_command_line_prints_one_json_line_per_controller(capsys):
    import json

    args = ["greedy", "random", "--grid", "8", "--walls", "1", "--num-envs", "4", "--max-steps", "20"]
    assert main(args) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [d["controller"] for d in lines] == ["greedy", "random"]
    assert all(d["episodes"] == 4 and 0.0 <= d["success_rate"] <= 1.0 for d in lines)
