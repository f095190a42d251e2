"""The floor of a benchmark episode: the moves a team that knows where the source is needs.

Every agent walks the shortest path of the environment's moves (8 directions, onto free cells) to
the nearest cell within the success radius (1.1 m) of the source; the episode's floor is the
fewest moves any agent of the team needs. No searcher can do better on average, so the floor shows
how much room a set leaves between a searcher and perfect knowledge.

    python -m medc_training.radbench.floor --grid 20 --agents 3 --episodes 40
    python -m medc_training.radbench.floor --sets-file DIR/g20-a3.json --episodes 16

prints the mean floor per obstruction count, for 5-7 obstructions and over all episodes; the last
line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np
import torch

from medc_training.envs.grid import bfs_distance

from .scenario import SUCCESS_M, Episode

__all__ = ["episode_floor", "floor_table"]


def episode_floor(episode: Episode, grid: int, cell_m: float = 1.0) -> int:
    """The fewest moves any agent of ``episode`` needs to stand within the success radius of its
    source, walking around the obstructions. Raises ValueError when no agent can get there."""
    walls = episode.walls(grid)
    rows, cols = np.mgrid[0:grid, 0:grid]
    d2_m = ((rows - episode.source[0]) ** 2 + (cols - episode.source[1]) ** 2) * cell_m**2
    goal = (d2_m <= SUCCESS_M**2 + 1e-9) & ~walls
    dist = bfs_distance(torch.from_numpy(~walls)[None], torch.from_numpy(goal)[None])[0]
    best = min(float(dist[r, c]) for r, c in episode.starts)
    if not np.isfinite(best):
        raise ValueError("no agent of the episode can reach its source")
    return int(best)


def floor_table(sets: list) -> dict[str, Any]:
    """Mean floor per obstruction count (over every set of that count), on 5-7 obstructions and over
    all the episodes of ``sets`` (:class:`~medc_training.radbench.sets.BenchSet`)."""
    by_count: dict[int, list[int]] = {}
    for bench_set in sets:
        floors = [episode_floor(e, bench_set.grid, bench_set.cell_m) for e in bench_set.episodes]
        by_count.setdefault(bench_set.obstructions, []).extend(floors)
    every = [v for values in by_count.values() for v in values]
    hard = [v for count in (5, 6, 7) for v in by_count.get(count, [])]
    return {"per_count": {str(c): {"episodes": len(v), "mean_floor": float(np.mean(v))}
                          for c, v in sorted(by_count.items())},
            "obs5-7": float(np.mean(hard)) if hard else None,
            "all": float(np.mean(every)), "episodes": len(every)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.floor",
                                description=__doc__.split("\n\n")[0])
    from .sets import SetFileError, add_set_arguments, sets_from_args

    add_set_arguments(p)
    args = p.parse_args(argv)
    try:
        table = floor_table(sets_from_args(args))
    except (OSError, SetFileError, ValueError) as exc:
        print(f"floor: {exc}", file=sys.stderr)
        return 2
    for count, row in table["per_count"].items():
        print(f"{count} obstructions: mean floor {row['mean_floor']:.2f} moves ({row['episodes']} episodes)")
    if table["obs5-7"] is not None:
        print(f"5-7 obstructions: {table['obs5-7']:.2f}")
    print(f"all: {table['all']:.2f} ({table['episodes']} episodes)")
    print(json.dumps(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
