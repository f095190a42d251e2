"""The classical controllers on a run's own evaluation episodes (medc_lab.report.reference_play
controller_play) and the report's paired comparison of final policies with them
(medc_lab.report.references.versus_best): the controllers play exactly the episodes the
run's evaluations played, the cache is reused, and the paired difference is the hand-computed one."""

from __future__ import annotations

import json
import math

import pytest
import torch
from medc_lab.report.finder import eval_config
from medc_lab.report.reference_play import (
    CONTROLLER_PLAY,
    controller_env,
    controller_lengths,
    controller_play,
    episodes_key,
)
from medc_lab.report.references import CONTROLLERS, versus_best
from medc_training.config import TrainConfig
from medc_training.metrics import CSV_COLUMNS
from medc_training.ppo import EVAL_SEED_OFFSET, make_env_for
from medc_training.stats import t95

#: What defines an episode's start in target localization: source, team, layout, the source's
#: strength and the background (realistic sensing), and the first readings.
START = ("target", "positions", "walls", "strength", "background", "readings")


def _tiny(**extra) -> dict:
    """A run config with tiny evaluation episodes: 6 episodes on 4 environments (two rounds, the
    second partial); the 'maps' observation keeps no posterior, so the controllers' core differs."""
    return TrainConfig(agents=2, walls=1, grid=8, max_steps=12, eval_envs=4, eval_episodes=6, seed=7,
                       env_options={"sensing": "realistic"}, observation="maps", **extra).to_dict()


def _start(env) -> dict[str, torch.Tensor]:
    return {k: getattr(env, k).clone() for k in START}


def test_controllers_play_the_runs_own_evaluation_episodes_and_the_cache_is_reused(tmp_path, monkeypatch):
    import medc_training.controllers as controllers
    import medc_training.evaluate as evaluate
    from medc_training.evaluate import round_seed

    cfg = _tiny()
    c = TrainConfig.from_dict(cfg)
    seed = c.seed + EVAL_SEED_OFFSET
    # The run's evaluation environment, as the trainer makes it, and the controllers' core.
    run_env = make_env_for(c, c.eval_envs, seed, False)
    ctl_env = controller_env(c, seed)
    assert run_env.memory.log_post is None and ctl_env.memory.log_post is not None
    run_starts = []
    for r in range(2):  # the two rounds of play_episodes
        run_env.reset(seed=round_seed(seed, r))
        ctl_env.reset(seed=round_seed(seed, r))
        run_starts.append(_start(run_env))
        assert all(torch.equal(run_starts[-1][k], getattr(ctl_env, k)) for k in START)
    assert not torch.equal(run_starts[0]["target"], run_starts[1]["target"])  # two sets of episodes

    # What the controllers see at the start of each round is the run's episode starts.
    real = controllers.controller_policy
    seen: dict[str, list] = {}

    def spy(name, env, **options):
        policy = real(name, env, **options)

        def watched(obs, mask):
            if bool((env.t == 0).all()):  # the first move of a round
                seen.setdefault(name, []).append(_start(env))
            return policy(obs, mask)

        return watched

    monkeypatch.setattr(controllers, "controller_policy", spy)
    played = controller_play(tmp_path, cfg)
    assert sorted(played) == sorted(CONTROLLERS) and sorted(seen) == sorted(CONTROLLERS)
    for name in CONTROLLERS:
        assert len(seen[name]) == 2
        for got, want in zip(seen[name], run_starts):
            assert all(torch.equal(got[k], want[k]) for k in START)
        assert len(played[name]["lengths"]) == len(played[name]["successes"]) == 6
        assert all(1 <= n <= 12 for n in played[name]["lengths"])
    cache = json.loads((tmp_path / CONTROLLER_PLAY).read_text())
    assert list(cache) == [episodes_key(cfg, None)] and cache[episodes_key(cfg, None)] == played

    # A second time nothing is played: everything comes from the cache.
    def refuse(*args, **kwargs):
        raise AssertionError("played again")

    monkeypatch.setattr(evaluate, "play_episodes", refuse)
    text = (tmp_path / CONTROLLER_PLAY).read_text()
    assert controller_play(tmp_path, cfg) == played
    assert (tmp_path / CONTROLLER_PLAY).read_text() == text
    lengths = controller_lengths(tmp_path, [{"config": cfg}])
    assert lengths == [{n: sum(played[n]["lengths"]) / 6 for n in CONTROLLERS}]


def _fake_seed(out, name: str, cfg: dict, curve: list[float]) -> None:
    d = out / "runs" / name / f"seed{cfg['seed']}"
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"config": cfg, "train_seconds": 1.0}))
    with (d / "metrics.csv").open("w") as f:
        f.write(",".join(CSV_COLUMNS) + "\n")
        for i, length in enumerate(curve):
            row = {"step": i * 10, "episode_length": length}
            f.write(",".join(str(row.get(col, "")) for col in CSV_COLUMNS) + "\n")


def test_final_policies_are_compared_with_the_controllers_on_each_seeds_own_episodes(tmp_path, monkeypatch):
    import medc_training.evaluate as evaluate
    from medc_lab.report.finder import load_curves

    monkeypatch.setattr(evaluate, "play_episodes", lambda *a, **k: pytest.fail("nothing is played"))
    base = TrainConfig(agents=3, walls=2, grid=8, max_steps=50, eval_envs=2, eval_episodes=2,
                       env_options={"sensing": "realistic"}).to_dict()
    # final levels (mean of the last three evaluations): 20, 22, 24
    curves = {0: [45.0, 21.0, 20.0, 19.0], 1: [45.0, 22.0, 22.0, 22.0], 2: [45.0, 25.0, 24.0, 23.0]}
    # each seed's two evaluation episodes: infotaxis 18, 19, 23 steps; greedy 25; gradient 40
    infotaxis = {0: [17, 19], 1: [19, 19], 2: [22, 24]}
    cache = {}
    for k, curve in curves.items():
        cfg = {**base, "seed": k}
        _fake_seed(tmp_path, "team", cfg, curve)
        cache[episodes_key(cfg, None)] = {
            "infotaxis": {"lengths": infotaxis[k], "successes": [True, True]},
            "greedy": {"lengths": [25, 25], "successes": [True, True]},
            "gradient": {"lengths": [40, 40], "successes": [False, False]}}
    (tmp_path / CONTROLLER_PLAY).write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    _, got_curves, summaries = load_curves(tmp_path, "team")
    played = controller_lengths(tmp_path, summaries)
    assert played == [{"gradient": 40.0, "greedy": 25.0, "infotaxis": m} for m in (18.0, 19.0, 23.0)]
    # paired differences 2, 3, 1: mean 2, sd 1, half-width t95(2) / sqrt(3)
    half = t95(2) / math.sqrt(3)
    final_half = t95(2) * 2 / math.sqrt(3)  # finals 20, 22, 24: sd 2
    ctl_half = t95(2) * math.sqrt(7) / math.sqrt(3)  # infotaxis 18, 19, 23: sd sqrt(7)
    line = versus_best("team", got_curves, played)
    assert line == (f"team: final 22.00 ± {final_half:.2f} steps, not resolved against infotaxis "
                    f"(20.00 ± {ctl_half:.2f} on the same episodes): +2.00 ± {half:.2f} (n = 3 seeds)")
    # the same differences 10 steps lower beat it; 10 higher do not
    lower = [[x - 10 for x in c] for c in got_curves]
    assert "beats infotaxis" in versus_best("team", lower, played)
    assert ": -8.00 ± " in versus_best("team", lower, played)
    higher = [[x + 10 for x in c] for c in got_curves]
    assert "does not beat infotaxis" in versus_best("team", higher, played)
    # the best controller is the best on these episodes
    swapped = [{**p, "greedy": p["infotaxis"] - 1} for p in played]
    assert "does not beat greedy (19.00 ± " in versus_best("team", got_curves, swapped)
    assert versus_best("team", got_curves, None) is None
    assert versus_best("team", got_curves, [{}, {}, {}]) is None  # no controller played


def test_an_frl_side_users_curve_is_compared_on_that_users_episodes():
    cfg = _tiny(method="frl", frl_users=[{"agents": 2, "walls": 1}, {"agents": 3, "walls": 2}])
    assert eval_config(cfg, "metrics.csv") is cfg
    side = eval_config(cfg, "metrics_A3W2.csv")
    assert (side["agents"], side["walls"], side["seed"]) == (3, 2, cfg["seed"])
    with pytest.raises(ValueError, match="no FRL user"):
        eval_config(cfg, "metrics_A1W3.csv")
