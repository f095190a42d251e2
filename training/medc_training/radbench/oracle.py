"""The benchmark's oracle: the fewest team moves in which any team could end an episode found.

A diagnostic lower bound, not a searcher: the oracle knows the source's cell and walks the team
straight to it, so its length is what no policy can beat on that episode, whatever its readings.
It follows the rules of the world that plays the frozen sets
(:class:`~medc_training.radbench.play.BenchCore`, a :class:`~medc_training.envs.target_localization.
TargetLocalization` core), through the world's own functions:

- **moves**: each agent makes one of the 8 one-cell moves per team step, all agents at once; a
  move is allowed when it lands on a free cell inside the grid (:func:`~medc_training.envs.grid.
  move_mask`), so a diagonal move past an obstruction's corner is allowed when its cell is free;
  agents may share a cell.
- **found**: after a team step, an agent within the success radius of the source (1.1 m:
  :meth:`~medc_training.envs.tl_sensing.SensingModel.within_reach`, here the source's cell and its
  four side neighbours) ends the episode found; the starts are not checked, so an episode lasts at
  least one move, and its length is the number of team steps made.
- **limit**: an episode not found after ``max_steps`` moves (120) fails at that length.

Hence the oracle's length is the minimum over agents and over an agent's allowed first moves of
1 + the BFS distance (8-connected moves through free cells, :func:`~medc_training.envs.grid.
bfs_distance`) from that move's cell to the nearest success cell: for an agent not on a success
cell, its BFS distance to the success cells.

    python -m medc_training.radbench.oracle --episodes 40 --out /tmp/oracle-g20-a3.episodes.jsonl

writes one ``medc-radbench`` episode line per episode (``"policy": "oracle"``, run 0), which
:mod:`medc_training.radbench.pairing` pairs with the lines of the policies played on the same sets;
``--verify`` also plays the oracle's moves through the benchmark's world and checks that each
episode ends found at the oracle's length.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import torch

from medc_training.envs.grid import (
    action_deltas,
    bfs_distance,
    grid_cells,
    move_mask,
    neighbour_index,
    pad_blocked,
)
from medc_training.envs.tl_sensing import SensingModel

from .pairing import GROUPS, episode_record
from .physics import TEAM_SENSING, episode_tensors
from .results import EpisodeResult, summarize
from .sets import BenchSet

__all__ = ["POLICY", "move_costs", "oracle_policy", "oracle_results", "oracle_steps", "success_field"]

#: The policy name of the oracle's episode lines.
POLICY = "oracle"


def success_field(walls: torch.Tensor, target: torch.Tensor, sensing: SensingModel = TEAM_SENSING
                  ) -> torch.Tensor:
    """float32 [K,G,G]: the fewest moves from each cell to a free cell within ``sensing``'s success
    radius of the source (``walls`` bool [K,G,G], ``target`` int64 [K,2]); 0 on those cells, inf on
    walls and cells that cannot reach one."""
    k, g = walls.shape[:2]
    delta = grid_cells(g, walls.device).unsqueeze(0) - target.unsqueeze(1)  # [K,G²,2]
    goal = sensing.within_reach((delta * delta).sum(-1)).view(k, g, g)
    return bfs_distance(~walls, goal & ~walls)


def move_costs(walls: torch.Tensor, field: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """float32 [K,N,8]: per agent (``positions`` int64 [K,N,2]) and move, 1 + ``field`` at the cell
    the move lands on (the team steps until found if this agent finds the source, making that move
    first); inf for a move the world does not allow."""
    deltas = action_deltas(walls.device)
    k, n = positions.shape[:2]
    g = walls.shape[-1]
    padded = torch.nn.functional.pad(field, (1, 1, 1, 1), value=math.inf).view(k, -1)
    after = padded.gather(1, neighbour_index(positions, g, deltas).view(k, -1)).view(k, n, -1)
    allowed = move_mask(positions, pad_blocked(walls), deltas)
    return torch.where(allowed, after + 1.0, math.inf)


def oracle_steps(walls: torch.Tensor, target: torch.Tensor, positions: torch.Tensor,
                 sensing: SensingModel = TEAM_SENSING) -> torch.Tensor:
    """float32 [K]: the fewest team steps after which an agent is within the success radius (inf
    when no agent can get there), for episodes of ``walls`` [K,G,G], ``target`` [K,2] and agents at
    ``positions`` [K,N,2]."""
    field = success_field(walls, target, sensing)
    return move_costs(walls, field, positions).flatten(1).min(1).values


def oracle_results(bench_set: BenchSet, sensing: SensingModel = TEAM_SENSING) -> list[EpisodeResult]:
    """Per episode of ``bench_set``, in order: the oracle's result (length = :func:`oracle_steps`,
    success; an episode it cannot end within ``max_steps`` fails at ``max_steps``); no declaration
    and no tracking error."""
    lay = episode_tensors(bench_set.episodes, bench_set.grid, max(1, bench_set.obstructions), "cpu")
    steps = oracle_steps(lay["walls"], lay["target"], lay["positions"], sensing).tolist()
    out = []
    for index, s in enumerate(steps):
        found = s <= bench_set.max_steps
        out.append(EpisodeResult(bench_set.id, index, int(s) if found else bench_set.max_steps, found))
    return out


def oracle_policy(core) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """An evaluator policy (:data:`medc_training.evaluate.Policy`: scores [B·N, 8] from observations
    and masks [B·N, 8]) for a target-localization ``core``: every agent takes an allowed move that
    brings it fastest within the success radius (read from the core's walls, source and positions),
    so the episode ends found at :func:`oracle_steps`. For checking the oracle against the world."""

    def scores(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        field = success_field(core.walls, core.target, core.sensing)
        cost = move_costs(core.walls, field, core.positions).reshape(mask.shape)  # [B·N, 8]
        return torch.where(mask & cost.isfinite(), -cost, torch.where(mask, -1e9, -math.inf))

    return scores


def _line(bench_set: BenchSet, result: EpisodeResult) -> str:
    return json.dumps(episode_record(POLICY, bench_set, result)) + "\n"


def _verify(bench_set: BenchSet, results: list[EpisodeResult]) -> None:
    """Play the oracle's moves through the benchmark's world; RuntimeError where an episode does not
    end as :func:`oracle_results` says."""
    from .play import play_set

    played = play_set(bench_set, oracle_policy)
    for want, got in zip(results, played):
        if (want.length, want.success) != (got.length, got.success):
            raise RuntimeError(f"episode {want.index} of {bench_set.id}: the oracle says "
                               f"{(want.length, want.success)}, the world played {(got.length, got.success)}")


def main(argv: list[str] | None = None) -> int:
    from medc_training.outfiles import AtomicOutput, check_output

    from .sets import SetFileError, add_set_arguments, sets_from_args

    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.oracle",
                                description=__doc__.split("\n\n")[0])
    add_set_arguments(p, sha256=True)
    p.add_argument("--out", type=Path, help="write every episode here (medc-radbench episode lines)")
    p.add_argument("--overwrite", action="store_true", help="replace what is already at --out")
    p.add_argument("--verify", action="store_true",
                   help="also play the oracle's moves through the benchmark's world and check every length")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        sets = sets_from_args(args)
        played = {s.id: oracle_results(s) for s in sets}
        if args.verify:
            for s in sets:
                _verify(s, played[s.id])
        if args.out is not None:
            target = check_output(args.out, overwrite=args.overwrite)
            with AtomicOutput(target, overwrite=args.overwrite) as out:
                for s in sets:
                    for r in played[s.id]:
                        out.file.write(_line(s, r).encode())
    except (SetFileError, ValueError, OSError, RuntimeError) as exc:
        print(f"oracle: {exc}", file=sys.stderr)
        return 2
    max_steps = sets[0].max_steps
    where = Path(sets[0].source).name if sets[0].source else "the set file"
    print(f"oracle on {where}: grid {sets[0].grid}, {sets[0].agents} agent(s), "
          f"{len(sets)} set(s) x {len(sets[0].episodes)} episodes"
          + ("; every length checked against the world" if args.verify else ""))
    groups = {**GROUPS, "all": tuple(sorted({s.obstructions for s in sets}))}
    for name, counts in groups.items():
        rows = [r for s in sets if s.obstructions in counts for r in played[s.id]]
        if not rows:
            continue
        f = summarize(rows, max_steps)
        lengths = [r.length for r in rows]
        median = f["median_completed_length"]
        print(f"  {name:<7} mean {f['mean_length']:.2f} ± {f['mean_length_ci95'] or 0.0:.2f}, median "
              f"{'-' if median is None else f'{median:g}'}, range {min(lengths)}-{max(lengths)}, found "
              f"{f['completed']}/{f['episodes']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
