"""The team's declarations are right as often as they claim (medc_lab.studies.calibration): on fixed
episodes of both sensing presets, the declarations at thresholds 0.9, 0.95 and 0.99 are right at a
rate whose Wilson 95 % interval reaches the threshold."""

from __future__ import annotations

import pytest
from medc_lab.studies.calibration import reliability, wilson
from medc_training.controllers import controller_policy
from medc_training.declaration_eval import threshold_episodes
from medc_training.envs import make_batched

THRESHOLDS = (0.9, 0.95, 0.99)


def study(sensing, episodes: int, **options) -> dict:
    """The greedy team's declarations on ``episodes`` fixed 13x13, 2-wall episodes ended by the
    declaration (the simulator's ``end_on: declaration``)."""
    env = make_batched("target_localization", num_envs=100, seed=7, agents=3, walls=2, grid=13, max_steps=60,
                       sensing=sensing, posterior=True, end_on_find=False, **options)
    rows = threshold_episodes(env, controller_policy("greedy", env), episodes=episodes, seed=7,
                              thresholds=THRESHOLDS)
    return reliability(rows, THRESHOLDS)


def test_wilson_interval():
    assert wilson(0, 0) == (0.0, 1.0)
    lo, hi = wilson(95, 100)
    assert lo == pytest.approx(0.8883, abs=1e-4) and hi == pytest.approx(0.9785, abs=1e-4)
    assert wilson(10, 10)[1] == 1.0 and wilson(0, 10)[0] == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("sensing, episodes, options", [
    # Unknown strength and background; with the 6 x 8 level grid this fails: 776 of 793 right at 0.99,
    # interval up to 0.987.
    ("realistic", 800, {}),
    ("paper-simple", 1000, {"noise": True}),
])
def test_declarations_are_right_as_often_as_they_claim(sensing, episodes, options, one_thread):
    result = study(sensing, episodes, **options)
    for row in result["thresholds"]:
        assert row["declared"] >= 0.9 * episodes, row
        # The interval's upper bound reaches the threshold: not measurably over-confident.
        assert row["calibrated"] and row["wilson"][1] >= row["threshold"], row
