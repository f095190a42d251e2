"""Reading the team's source posterior: where the team believes the source is, how sure it is, and
when it declares the source localised.

The posterior is :class:`~medc_training.envs.tl_observation.SourceEstimator`'s (``TeamMemory.posterior()``:
float32 [B, G²], cell index = row · G + col, rows summing to 1). Everything here is a pure, batched
function of it, shared by the ROS agent node (which publishes the estimate and the declaration) and
the batched evaluation of the declaration rule (:mod:`medc_training.declaration_eval`).

Declaration rule (:func:`declare`)
    With c the posterior's most probable (MAP) cell, the team declares the source localised when

        mass(c) = sum of p(s) over the cells s with |s - c| <= radius      >=  threshold

    |s - c| the Euclidean distance between cell centres, in cells. Defaults: ``radius`` = the sensing
    preset's success radius (0 for ``paper-simple``: the MAP cell alone; 1.1 for ``realistic``: the
    cell and its 4 edge neighbours), so a declaration says "a UAV flown to this cell finds the
    source with probability >= threshold"; ``threshold`` = :data:`DEFAULT_THRESHOLD`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Posterior mass within the radius that makes the team declare (docs/ros-reference.md, "The team's source
#: estimate", which gives the measured errors and times).
DEFAULT_THRESHOLD = 0.95


def _check(p: torch.Tensor, grid: int) -> None:
    if p.dim() != 2 or p.shape[1] != grid * grid:
        raise ValueError(f"posterior must be [B, {grid * grid}] for a {grid}x{grid} grid, "
                         f"got {tuple(p.shape)}")


def map_cells(p: torch.Tensor, grid: int) -> torch.Tensor:
    """int64 [B, 2]: the (row, col) of each posterior's most probable cell (the lowest index on a tie)."""
    _check(p, grid)
    idx = p.argmax(1)
    return torch.stack((idx // grid, idx % grid), dim=-1)


def mass_within(p: torch.Tensor, grid: int, cells: torch.Tensor, radius: float) -> torch.Tensor:
    """float32 [B]: posterior mass of the cells within Euclidean ``radius`` (cells, between centres)
    of ``cells`` int64 [B, 2] (row, col)."""
    _check(p, grid)
    if not radius >= 0:
        raise ValueError(f"radius must be a non-negative number of cells, got {radius!r}")
    idx = torch.arange(grid * grid, device=p.device)
    rows, cols = idx // grid, idx % grid
    dr = (rows.unsqueeze(0) - cells[:, :1]).float()
    dc = (cols.unsqueeze(0) - cells[:, 1:]).float()
    near = dr * dr + dc * dc <= float(radius) ** 2 + 1e-9
    return (p * near).sum(1)


@dataclass(frozen=True)
class Declaration:
    """:func:`declare`'s verdict for B posteriors: ``declared`` bool [B], ``cell`` int64 [B, 2]
    (row, col: the MAP cell, whether declared or not), ``mass`` float32 [B] within the radius."""

    declared: torch.Tensor
    cell: torch.Tensor
    mass: torch.Tensor


def check_rule(radius: float, threshold: float) -> tuple[float, float]:
    """Validate a declaration rule; returns (radius, threshold) as floats.

    Raises:
        ValueError: radius negative or not finite, threshold outside (0, 1].
    """
    radius, threshold = float(radius), float(threshold)
    if not (0.0 <= radius < float("inf")):
        raise ValueError(f"declaration radius must be a finite number of cells >= 0, got {radius!r}")
    if not (0.0 < threshold <= 1.0):
        raise ValueError(f"declaration threshold must be a probability in (0, 1], got {threshold!r}")
    return radius, threshold


def declare(p: torch.Tensor, grid: int, radius: float, threshold: float = DEFAULT_THRESHOLD) -> Declaration:
    """The declaration rule (module docstring) on posteriors float32 [B, G²]."""
    radius, threshold = check_rule(radius, threshold)
    cell = map_cells(p, grid)
    mass = mass_within(p, grid, cell, radius)
    return Declaration(mass >= threshold, cell, mass)


def mean_and_covariance(p: torch.Tensor, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean float64 [B, 2], covariance float64 [B, 2, 2]) of the source's (row, col) under the
    posteriors [B, G²], cell centres as points (in cells; a consumer adds the spread within a cell,
    1/12 cell² per axis, when it wants the source's position rather than its cell)."""
    _check(p, grid)
    q = p.double()
    q = q / q.sum(1, keepdim=True).clamp_min(1e-300)
    idx = torch.arange(grid * grid, device=p.device)
    rc = torch.stack((idx // grid, idx % grid), dim=-1).double()  # [G², 2]
    mean = q @ rc  # [B, 2]
    centred = rc.unsqueeze(0) - mean.unsqueeze(1)  # [B, G², 2]
    cov = torch.einsum("bk,bki,bkj->bij", q, centred, centred)
    return mean, cov
