"""The play loops: the product's one evaluator, play_episodes' fixed episodes, each played to its
end (medc_training.evaluate); the harness's legacy window (medc_lab.window), its two stopping rules
and the samplers; and that the window evaluation and random baseline still reproduce the
committed numbers."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from medc_lab.window import play
from medc_training.bundle import load_bundle
from medc_training.config import TrainConfig
from medc_training.envs import make_batched
from medc_training.envs.target_localization import SUCCESS_REWARD
from medc_training.evaluate import (
    PlayResult,
    env_for_bundle,
    evaluate_policy,
    net_policy,
    play_episodes,
    round_seed,
)
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


def test_committed_runs_read_as_window_evaluated():
    """A config recorded before eval_episodes existed means the legacy window it was made with."""
    assert TrainConfig.from_dict({"seed": 1}).eval_episodes == 0
    assert TrainConfig.from_dict({"eval_episodes": 32}).eval_episodes == 32
    assert TrainConfig().eval_episodes > 0  # new configs evaluate on fixed episodes


def test_the_product_evaluates_a_window_run_only_through_the_harness(repo_root, monkeypatch):
    """Without the harness's window registered, a run with eval_episodes 0 is refused with the way
    out; registered, its evaluation is the window's."""
    import medc_training.evaluate as evaluate
    from medc_lab.window import evaluate_window

    assert evaluate.registered_evaluator("window") is evaluate_window
    cfg, _ = _committed_run(repo_root, "runs/A3W2-sparse/seed0")
    trainer = Trainer(cfg)
    monkeypatch.setattr(evaluate, "_REGISTERED", {})
    with pytest.raises(RuntimeError, match=r"the research harness keeps \(import medc_lab\.window"):
        trainer.evaluate()


def test_random_play_reproduces_the_committed_random_baseline(repo_root, tmp_path):
    """The gate's random baseline for a window-evaluated run is still the committed number; a run
    evaluated on fixed episodes gets random play on exactly its evaluation episodes."""
    from medc_lab.report.reference_play import random_play_length

    folder = repo_root / "docs" / "reproduction" / "runs" / "A3W2-sparse" / "seed0"
    config = json.loads((folder / "summary.json").read_text())["config"]
    committed = json.loads((repo_root / "docs" / "reproduction" / "random_play.json").read_text())
    seed = config["seed"] + EVAL_SEED_OFFSET
    key = next(k for k in committed if k.startswith("target_localization|agents=3|walls=2|")
               and k.endswith(f"seed={seed}"))
    assert random_play_length(tmp_path, config) == committed[key]
    assert list(json.loads((tmp_path / "random_play.json").read_text())) == [key]
    fixed = {**config, "eval_episodes": 40, "eval_envs": 16}
    cfg = TrainConfig.from_dict(fixed)
    env = make_env_for(cfg, cfg.eval_envs, seed, False)
    expected = play_episodes(env, None, episodes=40, greedy=False, seed=seed).summary()["episode_length"]
    assert random_play_length(tmp_path, fixed) == expected
    assert f"{key}|episodes=40|envs=16" in json.loads((tmp_path / "random_play.json").read_text())


class _FirstValidMove:
    """A policy that always takes its first valid move (N, else NE, ...): on the episodes of seed 4
    below it never finds the target."""

    def __call__(self, obs, mask):
        return torch.where(mask, -torch.arange(mask.shape[-1], dtype=torch.float32), 0.0)


def test_play_episodes_counts_episodes_longer_than_any_window():
    """Every episode lasts max_steps (the target is never found) and all of them are counted, where
    a window shorter than max_steps counts none."""
    env = make_batched("target_localization", num_envs=4, seed=1, agents=1, walls=0, grid=15, max_steps=40)
    assert play(env, _FirstValidMove(), steps=30, seed=4).lengths == ()
    result = play_episodes(env, _FirstValidMove(), episodes=10, seed=4)
    assert result.lengths == (40,) * 10 and not any(result.successes)
    assert result.summary()["episode_length"] == 40.0
    assert result.ci95()["episode_length"] == (40.0, 0.0)


def _starts(env, seed: int, rounds: int) -> list:
    """The initial positions of every environment in each of play_episodes' rounds."""
    starts = []
    for r in range(rounds):
        env.reset(seed=round_seed(seed, r))
        starts.extend(env.state(i).positions for i in range(env.num_envs))
    return starts


def test_play_episodes_plays_the_same_episodes_for_every_policy():
    """Episode i starts from the same state whoever plays it: the order is the episode order, not
    the finish order, and a random team and a greedy policy play the same episodes."""
    env = make_batched("target_localization", num_envs=3, seed=5, **TL)
    seen: dict[str, list] = {}

    class Recording:
        """An env that remembers each environment's start of every round (after reset)."""

        def __init__(self, name):
            self.name = name
            seen[name] = []

        def __getattr__(self, attr):
            return getattr(env, attr)

        def reset(self, seed=None):
            out = env.reset(seed=seed)
            seen[self.name].extend(env.state(i).positions for i in range(env.num_envs))
            return out

    random = play_episodes(Recording("random"), None, episodes=7, seed=11)
    noisy = play_episodes(Recording("noisy"), lambda obs, mask: torch.randn(mask.shape), episodes=7, seed=11)
    assert seen["random"] == seen["noisy"] == _starts(env, 11, 3)
    assert len(set(map(tuple, seen["random"]))) > 1  # the rounds and environments differ
    assert random != noisy  # the same episodes, played differently


def test_play_episodes_returns_exactly_e_episodes_in_episode_order_and_is_deterministic():
    env = make_batched("target_localization", num_envs=4, seed=1, **TL)
    result = play_episodes(env, None, episodes=10, seed=3)  # 10 is not a multiple of 4: 3 rounds
    assert len(result.lengths) == len(result.successes) == len(result.returns) == 10
    for length, success, ret in zip(result.lengths, result.successes, result.returns):
        assert 1 <= length <= TL["max_steps"]
        assert ret == (SUCCESS_REWARD if success else 0.0)
        assert success or length == TL["max_steps"]
    assert play_episodes(env, None, episodes=10, seed=3) == result
    # more episodes from the same seed start with the same ones (rounds are seeded by their index)
    assert play_episodes(env, None, episodes=12, seed=3).lengths[:10] == result.lengths
    assert play_episodes(env, None, episodes=10, seed=4) != result
    # episodes 0..3 are the first episode of each environment after a reset from the seed itself
    first = {}
    play(env, None, steps=TL["max_steps"], seed=3,
         on_step=lambda a, out: [first.setdefault(int(i), int(out.episode_length[i]))
                                 for i in out.done.nonzero(as_tuple=True)[0]])
    assert tuple(first[i] for i in range(4)) == result.lengths[:4]
    summary = result.summary()
    ci = result.ci95()
    assert summary["episodes"] == 10 and ci["episode_length"][0] == pytest.approx(summary["episode_length"])
    assert ci["success_rate"][0] == pytest.approx(summary["success_rate"]) and ci["episode_length"][1] > 0


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
    by_net = play_episodes(env_for_bundle(bundle, num_envs=8, seed=5), net_policy(bundle.net), episodes=24,
                           seed=5)
    ci = by_net.ci95()
    assert {**by_net.summary(), "episode_length_ci95": ci["episode_length"][1],
            "success_rate_ci95": ci["success_rate"][1]} == by_bundle
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
    ({"episodes": 0}, "episodes must be a positive integer"),
    ({"episodes": 2.0}, "episodes must be a positive integer"),
    ({"episodes": 4, "sampling": "softmax"}, "sampling must be one of"),
])
def test_play_episodes_refuses_bad_arguments(kwargs, words):
    env = make_batched("target_localization", num_envs=1, seed=0, **TL)
    with pytest.raises(ValueError, match=words):
        play_episodes(env, None, **kwargs)


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
