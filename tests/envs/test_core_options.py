"""The three env cores check their common options (grid, agents, max_steps) with one check:
the same mistake gets the same message from each."""

from __future__ import annotations

import re

import pytest
from medc_training.envs import ENV_NAMES, make_batched
from medc_training.envs.core import MAX_EPISODE_STEPS

#: Each core's grid range and most agents on its smallest grid (what the one check enforces).
LIMITS = {
    "target_localization": (5, 256, 5 * 5 // 4),
    "fleet_coordination": (3, 64, 3 * 3 // 2),
    "maze_cleaning": (3, 64, 2 * 2),
}
#: The options each core takes besides the common ones, set so that they fit the smallest grid.
OWN = {"target_localization": {"walls": 0}, "fleet_coordination": {"customers": 1, "capacity": 1},
       "maze_cleaning": {}}


@pytest.mark.parametrize("name", ENV_NAMES)
@pytest.mark.parametrize("option, value, words", [
    ("grid", "low", "grid must be an integer in {lo}..{hi}, got {value}"),
    ("grid", "high", "grid must be an integer in {lo}..{hi}, got {value}"),
    ("agents", 0, "agents must be an integer in 1..{most}, got 0"),
    ("agents", True, "agents must be an integer in 1..{most}, got True"),
    ("max_steps", 0, f"max_steps must be an integer in 1..{MAX_EPISODE_STEPS}, got 0"),
    ("max_steps", 2.5, f"max_steps must be an integer in 1..{MAX_EPISODE_STEPS}, got 2.5"),
])
def test_every_core_checks_its_common_options_the_same_way(name: str, option, value, words) -> None:
    lo, hi, most = LIMITS[name]
    value = {"low": lo - 1, "high": hi + 1}.get(value, value) if isinstance(value, str) else value
    options = {"grid": lo, "agents": 1, "max_steps": 10, **OWN[name], option: value}
    message = words.format(lo=lo, hi=hi, most=most, value=value)
    with pytest.raises(ValueError, match=re.escape(message)):
        make_batched(name, num_envs=1, seed=0, **options)
    if option == "agents" and value == 0:  # the most agents the smallest grid takes are accepted
        make_batched(name, num_envs=1, seed=0, **{**options, "agents": most})


@pytest.mark.parametrize("name", ["fleet_coordination", "maze_cleaning"])
def test_the_observation_option_works_for_every_application_or_is_refused(name: str) -> None:
    """`medc-train --env maze_cleaning --observation ego9` trains on the 19x19 windows, and a view
    the application lacks (the source estimate, the source posterior) is refused, never replaced by
    'maps' silently."""
    from medc_training.cli.train import build_parser, config_from_args
    from medc_training.ppo import make_env_for

    for flag, side in (("ego9", 19), ("maps", 10)):
        args = build_parser().parse_args(["--out", "x", "--env", name, "--grid", "10", "--observation", flag])
        env = make_env_for(config_from_args(args), 2, 0, False)
        assert env.observation_name == flag
        assert env.obs_shape[1:] == (side, side)
    for view in ("ego6+estimate", "ego6+posterior", "maps+estimate+posterior"):
        args = build_parser().parse_args(["--out", "x", "--env", name, "--grid", "10", "--observation", view])
        with pytest.raises(ValueError, match="has no source estimate"):
            make_env_for(config_from_args(args), 2, 0, False)
    # Without the flag the application keeps its own default.
    args = build_parser().parse_args(["--out", "x", "--env", name, "--grid", "10"])
    assert make_env_for(config_from_args(args), 2, 0, False).observation_name == "maps"
