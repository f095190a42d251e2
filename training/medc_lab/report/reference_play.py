"""Reference play: random valid moves and the classical controllers on a run's own evaluation
episodes, each played once and cached in the report's folder (random_play.json,
controller_play.json), so that a rebuilt report plays nothing new."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from .finder import eval_config
from .references import CONTROLLERS

#: Random play's episodes per seed for the gate under the legacy window evaluator (the first to
#: finish); under fixed episodes random play plays the run's own evaluation episodes.
GATE_RANDOM_EPISODES = 256


def episodes_key(cfg: dict, episodes: int | None) -> str:
    """The key of a run's evaluation episodes (or of ``episodes`` fixed episodes of its evaluation
    seed) in OUT/random_play.json and OUT/controller_play.json."""
    from medc_training.config import TrainConfig
    from medc_training.ppo import EVAL_SEED_OFFSET

    c = TrainConfig.from_dict(cfg)
    key = (f"{c.env}|agents={c.agents}|walls={c.walls}|grid={c.grid}|max_steps={c.max_steps}|"
           f"{json.dumps(c.env_options, sort_keys=True)}|seed={c.seed + EVAL_SEED_OFFSET}")
    fixed = episodes or c.eval_episodes
    return key + (f"|episodes={fixed}|envs={c.eval_envs}" if fixed else "")


def random_play(out: Path, cfg: dict, episodes: int | None = None) -> dict:
    """{"episode_length", "success_rate"} of uniformly random valid moves on a run's evaluation
    episodes (its evaluation seed and environment), cached in OUT/random_play.json.

    With fixed-episode evaluation these are exactly the run's ``eval_episodes`` episodes, each
    played to its end (:func:`medc_training.evaluate.play_episodes`); a run evaluated with the
    legacy window (``eval_episodes`` 0) gets the legacy baseline it was gated with: the first
    GATE_RANDOM_EPISODES episodes to finish (:func:`medc_lab.window.play`). ``episodes``:
    that many fixed episodes of the run's evaluation seed instead of its own evaluation's. A cache
    entry written before success rates were kept holds the mean length alone: asked for both, the
    same episodes are played again (random play is seeded) and the entry holds both from then on."""
    from medc_training.config import TrainConfig
    from medc_training.evaluate import play_episodes
    from medc_training.ppo import EVAL_SEED_OFFSET, make_env_for

    from ..window import play

    key = episodes_key(cfg, episodes)
    cache_path = out / "random_play.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if not isinstance(cache.get(key), dict):
        c = TrainConfig.from_dict(cfg)
        seed = c.seed + EVAL_SEED_OFFSET
        env = make_env_for(c, c.eval_envs, seed, False)
        fixed = episodes or c.eval_episodes
        if fixed:
            played = play_episodes(env, None, episodes=fixed, greedy=False, seed=seed)
        else:
            played = play(env, None, episodes=GATE_RANDOM_EPISODES, greedy=False, seed=seed)
        summary = played.summary()
        cache[key] = {"episode_length": summary["episode_length"], "success_rate": summary["success_rate"]}
        cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return cache[key]


def random_play_length(out: Path, cfg: dict, episodes: int | None = None) -> float:
    """The mean episode length of :func:`random_play` (an entry cached with the length alone is
    read as it is: nothing is played again)."""
    cache_path = out / "random_play.json"
    cached = (json.loads(cache_path.read_text()) if cache_path.exists() else {}).get(
        episodes_key(cfg, episodes))
    if isinstance(cached, int | float):
        return float(cached)
    return float(random_play(out, cfg, episodes)["episode_length"])


#: The classical controllers' play on runs' evaluation episodes (:func:`controller_play`).
CONTROLLER_PLAY = "controller_play.json"


def controller_env(c, seed: int):
    """The batched core of config ``c`` (a :class:`~medc_training.config.TrainConfig`) on which the
    classical controllers play its evaluation episodes: the run's own evaluation environment
    (:func:`medc_training.ppo.make_env_for`, ``eval_envs`` environments, seeded ``seed``) with the
    team's source posterior kept, which the controllers read and which changes no episode."""
    from medc_training.ppo import make_env_for

    return make_env_for(c, c.eval_envs, seed, False, posterior=True)


def controllers_refuse(c) -> str | None:
    """Why the classical controllers cannot play the evaluation episodes of config ``c`` (a
    :class:`~medc_training.config.TrainConfig`); None when they can."""
    from medc_training.envs import application

    if not c.eval_episodes:
        return "a run evaluated with the legacy window has no fixed evaluation episodes"
    if not application(c.env).controllers:
        return f"the classical controllers read the team's source estimate; {c.env!r} keeps none"
    return None


def controller_play(out: Path, cfg: dict, controllers: Sequence[str] = CONTROLLERS) -> dict[str, dict]:
    """{controller: {"lengths", "successes"}} (per episode, in episode order) of each classical
    controller (:mod:`medc_training.controllers`, played greedily) on a run's evaluation episodes:
    its ``eval_episodes`` fixed episodes of its evaluation seed and environment
    (:func:`controller_env`), each played to its end, exactly as the run's evaluations played
    them (:func:`medc_training.evaluate.play_episodes`). Cached in OUT/controller_play.json by the
    episodes' key and controller; only what the cache lacks is played. Raises ValueError for a run
    evaluated with the legacy window (no fixed episodes) or of another application."""
    from medc_training.config import TrainConfig
    from medc_training.controllers import controller_policy
    from medc_training.evaluate import play_episodes
    from medc_training.ppo import EVAL_SEED_OFFSET

    c = TrainConfig.from_dict(cfg)
    refused = controllers_refuse(c)
    if refused:
        raise ValueError(refused)
    key = episodes_key(cfg, None)
    cache_path = out / CONTROLLER_PLAY
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    entry = cache.setdefault(key, {})
    seed = c.seed + EVAL_SEED_OFFSET
    env = None
    for name in controllers:
        if name in entry:
            continue
        env = env or controller_env(c, seed)
        played = play_episodes(env, controller_policy(name, env), episodes=c.eval_episodes, seed=seed)
        entry[name] = {"lengths": [int(x) for x in played.lengths],
                       "successes": [bool(x) for x in played.successes]}
        cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return {name: entry[name] for name in controllers}


def controller_lengths(out: Path, summaries: Sequence[dict], csv_name: str = "metrics.csv"
                       ) -> list[dict[str, float]] | None:
    """Per seed (``summaries``: one summary.json each), each classical controller's mean episode
    length on the evaluation episodes behind that seed's ``csv_name`` (:func:`controller_play`);
    None when a seed has no fixed evaluation episodes or its application keeps no source estimate."""
    from medc_training.config import TrainConfig

    lengths = []
    for summary in summaries:
        cfg = eval_config(summary["config"], csv_name)
        if controllers_refuse(TrainConfig.from_dict(cfg)):
            return None
        played = controller_play(out, cfg)
        lengths.append({name: sum(p["lengths"]) / len(p["lengths"]) for name, p in played.items()})
    return lengths
