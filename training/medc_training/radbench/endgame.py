"""A learned team with a classical endgame: a probe of where the team's moves go.

Until the team's source posterior says where to stand with probability ``tau``, the bundle decides
every move; from then on every agent that can reach such a place walks a shortest path towards it
through free cells, by the world's own moves (the oracle's :func:`~medc_training.radbench.oracle.
move_costs` over a breadth-first field), and the bundle decides again as soon as the posterior says
less (a wrong place is left when the readings there say so). Two triggers (:data:`TRIGGERS`):

- ``mode`` (the default): the posterior's mode holds at least ``tau`` of its mass; the places are
  the mode's success region (:func:`~medc_training.radbench.oracle.success_field` with the mode in
  place of the source).
- ``region``: some free cell has at least ``tau`` of the mass within its success radius (the
  probability that an agent standing there has found the source); the places are every such cell.
  A mode holding ``tau`` makes its whole success region such places, so this trigger plans wherever
  ``mode`` does, and earlier where the mass is spread over a few neighbouring cells.

``tau`` = 1 never plans: the team alone. The team's memory is the one its observations are built
from, so nothing the endgame reads is hidden from the team.

    python -m medc_training.radbench.endgame BUNDLE --tau 0.9 [--trigger region] --sets-file F \
        --out E.episodes.jsonl

writes ``medc-radbench`` episode lines (policy ``<bundle's folder>+endgame<tau>``, ``-region`` added
under that trigger), which ``python -m medc_training.radbench.pairing`` pairs with the bundle's own
lines on the same episodes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import torch

from medc_training.envs.grid import bfs_distance

from .oracle import move_costs, success_field

__all__ = ["TRIGGERS", "Endgame", "agent_move", "check_tau", "check_trigger", "planned_costs",
           "standing_mass"]

#: What starts the endgame (module docstring).
TRIGGERS: tuple[str, ...] = ("mode", "region")


def check_tau(tau: Any, what: str = "the endgame's tau") -> float:
    """``tau`` as a float in (0, 1] (1: never plan); ValueError naming it as ``what`` otherwise."""
    if isinstance(tau, bool) or not isinstance(tau, int | float) or not 0.0 < tau <= 1.0:
        raise ValueError(f"{what} must be a number in (0, 1] (1: never plan), got {tau!r}")
    return float(tau)


def check_trigger(trigger: Any, what: str = "the endgame's trigger") -> str:
    """``trigger`` if it is one of :data:`TRIGGERS`; ValueError naming it as ``what`` otherwise."""
    if trigger not in TRIGGERS:
        raise ValueError(f"{what} must be one of {', '.join(TRIGGERS)}, got {trigger!r}")
    return trigger


def standing_mass(posterior: torch.Tensor, walls: torch.Tensor, sensing: Any) -> torch.Tensor:
    """float32 [B,G,G]: per free cell of ``walls`` bool [B,G,G], the mass of ``posterior`` float32
    [B,G²] within ``sensing``'s success radius of it (the probability that an agent standing there
    has found the source); 0 on walls."""
    b, g = walls.shape[0], walls.shape[-1]
    r = int(sensing.success_radius)
    offsets = torch.arange(-r, r + 1, device=walls.device)
    d2 = offsets.view(-1, 1) ** 2 + offsets.view(1, -1) ** 2
    kernel = sensing.within_reach(d2).to(posterior.dtype).view(1, 1, 2 * r + 1, 2 * r + 1)
    mass = torch.nn.functional.conv2d(posterior.view(b, 1, g, g), kernel, padding=r).view(b, g, g)
    return mass.masked_fill(walls, 0.0)


def planned_costs(posterior: torch.Tensor, walls: torch.Tensor, positions: torch.Tensor, sensing: Any,
                  tau: float, trigger: str = "mode") -> tuple[torch.Tensor, torch.Tensor | None]:
    """Where the endgame plans, and what: (rows int64 [R], the episodes whose ``posterior`` float32
    [B,G²] starts the endgame under ``trigger`` (module docstring); cost float32 [R,N,8], per agent
    at ``positions`` int64 [B,N,2] and move, the fewest moves to the trigger's places through the
    free cells of ``walls`` bool [B,G,G], inf for a move not allowed or with no way there; None when
    R = 0)."""
    if trigger == "region":
        mass = standing_mass(posterior, walls, sensing)
        rows = (mass.flatten(1).amax(1) >= tau).nonzero().squeeze(1)
        if rows.numel() == 0:
            return rows, None
        free = ~walls[rows]
        field = bfs_distance(free, free & (mass[rows] >= tau))
        return rows, move_costs(walls[rows], field, positions[rows])
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
               tau: float, agent: int, mask: torch.Tensor, trigger: str = "mode") -> int | None:
    """One agent's endgame move in one episode (``posterior`` [1,G²], ``walls`` [1,G,G], the team at
    ``positions`` [1,N,2]; ``mask`` bool [8]: the agent's allowed moves), as an agent node decides it:
    the first allowed move with the fewest moves left, the evaluator's greedy choice over
    :func:`_move_scores`; None when ``tau`` >= 1, the posterior does not start the endgame under
    ``trigger`` or agent ``agent`` cannot reach the trigger's places."""
    if tau >= 1.0:
        return None
    from medc_training.nets import masked_logits

    _, cost = planned_costs(posterior, walls, positions, sensing, tau, trigger)
    if cost is None:
        return None
    own = cost[0, agent]  # [8]
    if not bool(own.isfinite().any()):
        return None
    return int(masked_logits(_move_scores(own).unsqueeze(0), mask.unsqueeze(0)).argmax(-1)[0])


class Endgame:
    """A play factory (:func:`~medc_training.radbench.play.play_set` takes it as a policy): the
    bundle's moves, and shortest-path moves to where the posterior says to stand once it says so
    with probability ``tau`` under ``trigger`` (module docstring). ``observation``: the bundle's,
    which the core makes; ``planned``: agent decisions the endgame took, of ``decisions`` (every
    agent's, while its episode runs or not)."""

    def __init__(self, bundle: Any, tau: float, trigger: str = "mode") -> None:
        self.bundle, self.tau, self.trigger = bundle, check_tau(tau), check_trigger(trigger)
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
                                       self.tau, self.trigger)
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
                   help="the posterior mass that starts the endgame (1: never)")
    p.add_argument("--trigger", choices=TRIGGERS, default="mode",
                   help="mode: the mass on the posterior's mode; region: the mass within the success "
                        "radius of a free cell (default: mode)")
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
        policy = Endgame(bundle, args.tau, args.trigger)
        sensing = policy_sensing(bundle, None if args.prior_background is None
                                 else team_sensing(args.prior_background))
        name = f"{Path(args.bundle).parent.name}+endgame{args.tau:g}" + (
            "" if args.trigger == "mode" else f"-{args.trigger}")
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
