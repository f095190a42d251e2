"""The radiation-search field's benchmark: RAD-A2C's scenarios on a grid, frozen test sets, and the
figures the field reports (docs/radbench.md).

- :mod:`~medc_training.radbench.scenario`: the physics in RAD-A2C's units, the SNR bins, and the
  seeded generator of episode definitions (obstructions, source, strength, background, starts,
  count-noise seed).
- :mod:`~medc_training.radbench.sets`: the committed sets (obstruction counts 0-7 x SNR bins low,
  medium, high, 200 episodes each, for 20 x 20 and 30 x 30 cells of 1 m and 1 or 3 agents), loaded
  only when their SHA-256 matches.
- :mod:`~medc_training.radbench.results`: completion rate, median completed length with its
  order-statistic interval, mean length with failures at the limit, declaration error and time,
  tracking error, and paired comparisons of two policies.
- :mod:`~medc_training.radbench.play`: a set played through the project's evaluator by random moves,
  a classical controller, a policy bundle or any policy factory.
- :mod:`~medc_training.cli.radbench`: ``medc-radbench``.

    from medc_training.radbench import load_sets, play_set, summarize
    (s,) = load_sets(grid=20, agents=1, obstructions=[3], snrs=["low"])
    results = play_set(s, "infotaxis", episodes=20)
    print(s.sha256, summarize(results, s.max_steps))
"""

from .play import TEAM_SENSING, BenchCore, play_set, poisson_counts
from .results import EpisodeResult, median_ci, paired, summarize
from .scenario import GRIDS, SNR_BINS, Episode, generate_set, snr, snr_bin
from .sets import BenchSet, SetFileError, load_file, load_sets

__all__ = [
    "GRIDS",
    "SNR_BINS",
    "TEAM_SENSING",
    "BenchCore",
    "BenchSet",
    "Episode",
    "EpisodeResult",
    "SetFileError",
    "generate_set",
    "load_file",
    "load_sets",
    "median_ci",
    "paired",
    "play_set",
    "poisson_counts",
    "snr",
    "snr_bin",
    "summarize",
]
