"""A learned team with a classical endgame: a probe of where the team's moves go.

Until the team's source posterior holds at least ``tau`` of its mass on one cell, the bundle
decides every move; from then on every agent that can reach that cell's success region walks a
shortest path towards it through free cells, by the world's own moves (the oracle's
:func:`~medc_training.radbench.oracle.success_field` and :func:`~medc_training.radbench.oracle.
move_costs`, with the posterior's mode in place of the source), and the bundle decides again as soon
as the mode holds less (a wrong mode is left when the readings there say so). ``tau`` = 1 never
plans: the team alone. The team's memory is the one its observations are built from, so nothing
the endgame reads is hidden from the team.

    python -m medc_training.radbench.endgame BUNDLE --tau 0.9 --sets-file F --out E.episodes.jsonl

writes ``medc-radbench`` episode lines (policy ``<bundle's folder>+endgame<tau>``), which
``python -m medc_training.radbench.pairing`` pairs with the bundle's own lines on the same episodes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import torch

from .oracle import move_costs, success_field

__all__ = ["Endgame", "agent_move", "check_tau", "planned_costs"]


def check_tau(tau: Any, what: str = "the endgame's tau") -> float:
    """``tau`` as a float in (0, 1] (1: never plan); ValueError naming it as ``what`` otherwise."""
    if isinstance(tau, bool) or not isinstance(tau, int | float) or not 0.0 < tau <= 1.0:
        raise ValueError(f"{what} must be a number in (0, 1] (1: never plan), got {tau!r}")
    return float(tau)


def planned_costs(posterior: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor, sensing: Any,
                  tau: float) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Where the endgame plans, and what: (rows int64 [R], the episodes whose ``posterior`` float32
    [B,G²] holds at least ``tau`` of its mass on one cell; cost float32 [R,N,8], per agent at
    ``positions`` int64 [B,N,2] and move, the fewest moves to the success region (``sensing``'s
    radius) of that cell through the free cells of ``walls`` bool [B,G,G], inf for a move not allowed
    or with no way there; None when R = 0)."""
    top, cell = posterior.max(1)
    rows = (top >= tau).nonzero().squeeze(1)
    if rows.numel() == 0:
        return rows, None
    g = walls.shape[-1]
    mode = torch.stack((cell[rows] // g, cell[rows] % g), 1)
    return rows, move_costs(walls[rows], success_field(walls[rows], mode, sensing), positions[rows])


def _move_scores(cost: torch.Tensor) -> torch.Tensor:
    """Scores whose greedy choice is a move with the fewest moves left (``cost`` [..., 8]; a move not
    allowed or with no way there scores lowest)."""
    return torch.where(cost.isfinite(), -cost, -1e9)


def agent_move(posterior: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor, sensing: Any,
               tau: float, agent: int, mask: torch.Tensor) -> int | None:
    """One agent's endgame move in one episode (``posterior`` [1,G²], ``walls`` [1,G,G], the team at
    ``positions`` [1,N,2]; ``mask`` bool [8]: the agent's allowed moves), as an agent node decides it:
    the first allowed move with the fewest moves left, the evaluator's greedy choice over
    :func:`_move_scores`; None when ``tau`` >= 1, the posterior's mode holds less than ``tau`` or
    agent ``agent`` cannot reach the mode's success region."""
    if tau >= 1.0:
        return None
    from medc_training.nets import masked_logits

    _, cost = planned_costs(posterior, walls, positions, sensing, tau)
    if cost is None:
        return None
    own = cost[0, agent]  # [8]
    if not bool(own.isfinite().any()):
        return None
    return int(masked_logits(_move_scores(own).unsqueeze(0), mask.unsqueeze(0)).argmax(-1)[0])


class Endgame:
    """A play factory (:func:`~medc_training.radbench.play.play_set` takes it as a policy): the
    bundle's moves, and shortest-path moves towards the posterior's mode once it holds ``tau``.
    ``observation``: the bundle's, which the core makes; ``planned``: agent decisions the endgame
    took, of ``decisions`` (every agent's, while its episode runs or not)."""

    def __init__(self, bundle: Any, tau: float) -> None:
        self.bundle, self.tau = bundle, check_tau(tau)
        self.observation = bundle.observation or "maps"
        self.planned = self.decisions = 0

    def __call__(self, core):
        from .play import core_policy

        net = core_policy(core, self.bundle, self.bundle)  # the bundle's shape checked against the core's
        n = core.num_agents

        def scores(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                logits = net(obs, mask)
            self.decisions += mask.shape[0]
            if self.tau >= 1.0:
                return logits
            rows, cost = planned_costs(core.memory.posterior(), core.walls, core.positions, core.sensing,
                                       self.tau)
            if cost is None:
                return logits
            reach = cost.isfinite().any(-1, keepdim=True)  # [R, N, 1]
            out = logits.view(-1, n, logits.shape[-1]).clone()
            out[rows] = torch.where(reach, _move_scores(cost), out[rows])
            self.planned += int(reach.sum())
            return out.view(-1, logits.shape[-1])

        return scores


def main(argv: list[str] | None = None) -> int:
    from medc_training.outfiles import AtomicOutput, check_output

    from .pairing import episode_record
    from .physics import team_sensing
    from .play import _bundle, play_set, policy_sensing
    from .sets import SetFileError, add_set_arguments, sets_from_args

    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.endgame",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("bundle", help="the team's policy bundle")
    p.add_argument("--tau", type=float, required=True,
                   help="the posterior mass on its mode that starts the endgame (1: never)")
    add_set_arguments(p, obstructions=True)
    p.add_argument("--prior-background", metavar="LOW,HIGH,LEVELS",
                   help="the team's estimator weighs this background prior (as medc-radbench takes it)")
    p.add_argument("--out", type=Path, required=True, help="write every played episode here (JSON lines)")
    p.add_argument("--overwrite", action="store_true", help="replace what is already at --out")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        sets = sets_from_args(args)
        bundle = _bundle(args.bundle)
        policy = Endgame(bundle, args.tau)
        sensing = policy_sensing(bundle, None if args.prior_background is None
                                 else team_sensing(args.prior_background))
        name = f"{Path(args.bundle).parent.name}+endgame{args.tau:g}"
        target = check_output(args.out, overwrite=args.overwrite)
        lengths = []
        with AtomicOutput(target, overwrite=args.overwrite) as out:
            for s in sets:
                for r in play_set(s, policy, sensing=sensing):
                    out.file.write((json.dumps(episode_record(name, s, r)) + "\n").encode())
                    lengths.append(r.length)
    except (SetFileError, ValueError, OSError) as exc:
        print(f"endgame: {exc}", file=sys.stderr)
        return 2
    print(f"{name}: {len(lengths)} episodes, mean {sum(lengths) / len(lengths):.3f} moves; the endgame took "
          f"{policy.planned:,} of {policy.decisions:,} decisions")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
