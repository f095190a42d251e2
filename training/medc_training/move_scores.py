"""How every controller turns its criterion into a move: the neighbour cells of each agent, a map's
values at them, and the tie rule that raises the chosen move's score just above the rest
(:mod:`medc_training.controllers` and :mod:`medc_training.searchers` share it)."""

from __future__ import annotations

import math

import torch

from medc_training.envs.grid import action_deltas

__all__ = ["at_cells", "choose_move", "expected_chebyshev", "neighbour_cells"]


def neighbour_cells(positions: torch.Tensor, grid: int) -> torch.Tensor:
    """int64 [...,8,2]: the cell after each move from ``positions`` int64 [...,2], clamped into the
    grid (invalid moves are masked by the caller)."""
    cells = positions.unsqueeze(-2) + action_deltas(positions.device)
    return cells.clamp(0, grid - 1)


def at_cells(maps: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """maps [B,G,G] (or [B,G²]) at cells int64 [B,...,2] -> [B,...]."""
    b = cells.shape[0]
    g = math.isqrt(maps[0].numel())
    flat = (cells[..., 0] * g + cells[..., 1]).reshape(b, -1)
    return maps.reshape(b, -1).gather(1, flat).view(cells.shape[:-1])


def choose_move(score: torch.Tensor, mask: torch.Tensor,
            keys: list[tuple[torch.Tensor, float | torch.Tensor]]) -> torch.Tensor:
    """``score`` [B,N,A] (-inf where ``mask`` is False) with the chosen move raised just above every
    other: the chosen move is the first, by action index, of those left after filtering the valid
    moves by each (key, tolerance) in turn (smaller key is better; a move stays while its key is
    within the tolerance of the best one left; a tolerance is a number or a tensor [B,N,1])."""
    tied = mask.clone()
    for key, tol in keys:
        k = key.masked_fill(~tied, float("inf"))
        tied &= k <= k.amin(-1, keepdim=True) + tol
    first = tied.to(torch.int8).argmax(-1, keepdim=True)  # the first True (argmax returns the first max)
    score = score.masked_fill(~mask, float("-inf"))
    best = score.amax(-1, keepdim=True)
    finite = torch.isfinite(best)
    best = torch.where(finite, best, torch.zeros_like(best))
    lifted = best + 1e-3 * best.abs().clamp(min=1.0)
    any_valid = mask.any(-1, keepdim=True)
    return score.scatter(-1, first, torch.where(any_valid, lifted, score.gather(-1, first)))


def expected_chebyshev(posterior: torch.Tensor, grid: int) -> torch.Tensor:
    """float32 [B,G²]: E(c) = sum_s p(s) max(|c_row - s_row|, |c_col - s_col|) for every cell c, from
    a posterior float32 [B,G²] (rows summing to 1): the team's estimate map before scaling
    (:meth:`~medc_training.envs.tl_observation.SourceEstimator.expected_from_posterior`)."""
    from medc_training.envs.tl_observation import SourceEstimator

    return SourceEstimator(grid, posterior.device).expected_from_posterior(posterior)
