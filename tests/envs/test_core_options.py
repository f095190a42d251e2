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
