"""The one play loop (medc_training.evaluate.play): its two stopping rules, its samplers, and that
every evaluation that plays through it reproduces the committed numbers."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from medc_training.bundle import load_bundle
from medc_training.config import TrainConfig
from medc_training.envs import make_batched
from medc_training.envs.target_localization import SUCCESS_REWARD
from medc_training.evaluate import PlayResult, env_for_bundle, evaluate_policy, net_policy, play
from medc_training.ppo import EVAL_SEED_OFFSET, Trainer, make_env_for

TL = dict(agents=2, walls=1, grid=8, max_steps=12)


def _committed_run(repo_root, run: str) -> tuple[TrainConfig, dict]:
    folder = repo_root / "docs" / "reproduction" / run
    cfg = TrainConfig.from_dict(json.loads((folder / "summary.json").read_text())["config"])
    with open(folder / "metrics.csv") as f:
        return cfg, next(csv.DictReader(f))


@pytest.mark.parametrize("run", ["runs/A3W2-sparse/seed0", "observation-probe-other/fleet-maps-mlp/seed0"])
def test_trainer_evaluation_reproduces_the_committed_first_evaluation(repo_root, run):
    """Greedy (target localization) and sampled (fleet) evaluation of the seed's initial network:
    the numbers the committed reproduction recorded at step 0."""
    cfg, row = _committed_run(repo_root, run)
    assert cfg.eval_greedy is (run.startswith("runs/"))
    ev = Trainer(cfg).evaluate()
    assert ev["episode_length"] == float(row["episode_length"])
    assert ev["success_rate"] == float(row["success_rate"])


def test_random_play_reproduces_the_committed_random_baseline(repo_root):
    cfg, _ = _committed_run(repo_root, "runs/A3W2-sparse/seed0")
    committed = json.loads((repo_root / "docs" / "reproduction" / "random_play.json").read_text())
    seed = cfg.seed + EVAL_SEED_OFFSET
    key = next(k for k in committed if k.startswith("target_localization|agents=3|walls=2|")
               and k.endswith(f"seed={seed}"))
    env = make_env_for(cfg, cfg.eval_envs, seed, False)
    played = evaluate_policy(env, None, 256, greedy=False, seed=seed)
    assert played["episodes"] == 256
    assert played["episode_length"] == committed[key]


def test_episodes_mode_keeps_the_first_episodes_and_their_returns():
    env = make_batched("target_localization", num_envs=4, seed=1, **TL)
    result = play(env, None, episodes=10, seed=3)
    assert isinstance(result, PlayResult)
    assert len(result.lengths) == len(result.successes) == len(result.returns) == 10
    for length, success, ret in zip(result.lengths, result.successes, result.returns):
        assert 1 <= length <= TL["max_steps"]
        # sparse reward: the team is paid once, when it finds the target
        assert ret == (SUCCESS_REWARD if success else 0.0)
        assert success or length == TL["max_steps"]
    # the same seed plays the same episodes; a longer run starts with them
    assert play(env, None, episodes=10, seed=3) == result
    assert play(env, None, episodes=20, seed=3).lengths[:10] == result.lengths
    summary = result.summary()
    assert summary["episodes"] == 10
    assert summary["episode_length"] == pytest.approx(sum(result.lengths) / 10)
    assert summary["success_rate"] == pytest.approx(sum(result.successes) / 10)


class _MaskChecked:
    """A real batched env that also counts the batched steps and the masked moves it is given."""

    def __init__(self, env) -> None:
        self.env, self.steps, self.masked_moves = env, 0, 0

    def __getattr__(self, name):
        return getattr(self.env, name)

    def reset(self, seed=None):
        obs, self.mask = self.env.reset(seed=seed)
        return obs, self.mask

    def step(self, actions):
        self.steps += 1
        self.masked_moves += int((~self.mask.gather(2, actions.unsqueeze(2))).sum())
        out = self.env.step(actions)
        self.mask = out.mask
        return out


def test_steps_mode_plays_exactly_that_many_steps_and_keeps_every_episode():
    env = _MaskChecked(make_batched("target_localization", num_envs=3, seed=2, **TL))
    steps = 2 * TL["max_steps"] + 5
    seen = []
    result = play(env, None, steps=steps, seed=4, on_step=lambda actions, out: seen.append((actions, out)))
    assert env.steps == steps
    # on_step saw every step: the actions given and what the env returned
    assert len(seen) == steps and all(a.shape == (3, TL["agents"]) for a, _ in seen)
    assert sum(int(out.done.sum()) for _, out in seen) == len(result.lengths)
    assert len(result.lengths) >= 3 * 2  # each episode lasts at most max_steps
    # every step of every environment belongs to a kept episode or to the one still running
    running = sum(env.state(i).step for i in range(3))
    assert sum(result.lengths) + running == 3 * steps
    # with no episode finished the summary says so and takes the given default length
    short = play(env, None, steps=1, seed=4)
    assert short.summary(default_length=TL["max_steps"]) == {
        "episodes": 0, "episode_length": float(TL["max_steps"]), "success_rate": 0.0, "episode_return": 0.0}


def test_policy_callable_bundle_and_net_policy_agree(repo_root):
    bundle = load_bundle(repo_root / "models" / "team" / "A3W2.safetensors")
    by_bundle = evaluate_policy(env_for_bundle(bundle, num_envs=8, seed=5), bundle, 24, greedy=True, seed=5)
    by_net = play(env_for_bundle(bundle, num_envs=8, seed=5), net_policy(bundle.net), episodes=24, seed=5)
    assert by_net.summary() == by_bundle
    assert by_bundle["success_rate"] > 0.9  # the shipped team finds the target


def test_policy_sees_every_agent_and_cannot_pick_a_masked_move():
    """The loop masks the policy's logits: a policy that prefers the invalid moves still moves
    validly, greedy or sampled; random play moves validly too."""
    env = _MaskChecked(make_batched("target_localization", num_envs=2, seed=6, **TL))
    shapes = []

    def wants_invalid(obs, mask):
        shapes.append(tuple(obs.shape))
        return torch.where(mask, 0.0, 100.0)  # the invalid moves score highest

    runs = ((wants_invalid, True, "multinomial"), (wants_invalid, False, "multinomial"),
            (wants_invalid, False, "gumbel"), (None, False, "multinomial"), (None, False, "gumbel"))
    for policy, greedy, sampling in runs:
        shapes.clear()
        play(env, policy, steps=30, greedy=greedy, seed=1, sampling=sampling)
        assert shapes == ([(2 * TL["agents"], *env.obs_shape)] * 30 if policy else [])
    assert env.steps == 5 * 30
    assert env.masked_moves == 0


def test_the_two_samplers_are_repeatable_and_draw_different_streams():
    env = make_batched("target_localization", num_envs=4, seed=7, **TL)
    multinomial = play(env, None, episodes=40, seed=9, sampling="multinomial")
    gumbel = play(env, None, episodes=40, seed=9, sampling="gumbel")
    assert play(env, None, episodes=40, seed=9, sampling="gumbel") == gumbel
    assert multinomial != gumbel
    # both are random valid moves: similar mean lengths over the same episodes' distribution
    assert abs(multinomial.summary()["episode_length"] - gumbel.summary()["episode_length"]) < 4


@pytest.mark.parametrize("kwargs, words", [
    ({}, "exactly one of episodes"),
    ({"episodes": 4, "steps": 4}, "exactly one of episodes"),
    ({"episodes": 0}, "episodes must be a positive integer"),
    ({"steps": True}, "steps must be a positive integer"),
    ({"episodes": 4, "sampling": "softmax"}, "sampling must be one of"),
])
def test_bad_arguments_are_refused(kwargs, words):
    env = make_batched("target_localization", num_envs=1, seed=0, **TL)
    with pytest.raises(ValueError, match=words):
        play(env, None, **kwargs)
