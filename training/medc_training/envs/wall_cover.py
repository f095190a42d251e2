"""Blocked cells of any map as a few axis-aligned rectangles, for the exact line-of-sight rule.

:func:`~medc_training.envs.tl_sensing.wall_rectangles` reads a map whose walls are straight segments
one cell thick that never touch (the grid world's). A map of solid obstructions that may touch or
overlap (the field benchmark's, a real UAV's) needs another decomposition: :func:`cover_rectangles`
covers exactly the blocked cells of any map with rectangles, in the same format.

Line of sight through the union of rectangles that cover exactly the blocked cells is the same
whatever the cover: a segment between two cell centres never runs along a cell edge (centres lie on
integers, edges on half-integers), so it meets the interior of the union exactly where it meets the
interior of one of the rectangles. The estimator reading a cover therefore sees what it sees with any
other exact cover of the same cells (the obstructions' own rectangles included).

**How many rectangles.** The cover is greedy: the first blocked cell not yet covered (row-major)
seeds a rectangle that grows right and then down (or down and then right, whichever covers more
cells not yet covered) over blocked cells, covered or not, and then grows left, up, right and down
while a whole blocked row or column borders it. Obstructions with a free cell between them (the
benchmark's generator keeps one) take one rectangle each, whatever their size; touching or overlapping
ones may take more than there are obstructions (:data:`OBSTRUCTION_SLOTS`).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["OBSTRUCTION_SLOTS", "cover_cells", "cover_rectangles"]

#: Rectangles a map of up to 7 obstructions (the benchmark's most) may take: twice as many. Separate
#: obstructions take one each; on maps of 7 rectangles of 2-5 cells a side placed at random, touching
#: and overlapping, on 20 x 20 and 30 x 30 grids, the greedy cover took at most 10 (tests/training/
#: test_wall_cover.py measures it). The estimator's line-of-sight test costs one comparison per slot.
OBSTRUCTION_SLOTS = 14


def cover_cells(walls: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Rectangles (top row, left column, bottom row, right column; inclusive) whose union is exactly
    the True cells of ``walls`` (bool [H,W]), by the greedy rule of the module docstring, in the
    row-major order of their seeds."""
    walls = np.asarray(walls, dtype=bool)
    h, w = walls.shape
    covered = np.zeros_like(walls)
    out: list[tuple[int, int, int, int]] = []
    while True:
        left = np.flatnonzero((walls & ~covered).ravel())
        if left.size == 0:
            return out
        r, c = divmod(int(left[0]), w)
        best = None
        for first in ("right", "down"):
            rect = _grow(walls, _seed_rect(walls, r, c, first), h, w)
            gain = int((~covered[rect[0]:rect[2] + 1, rect[1]:rect[3] + 1]).sum())
            if best is None or gain > best[0]:
                best = (gain, rect)
        r0, c0, r1, c1 = best[1]
        covered[r0:r1 + 1, c0:c1 + 1] = True
        out.append((r0, c0, r1, c1))


def _seed_rect(walls: np.ndarray, r: int, c: int, first: str) -> tuple[int, int, int, int]:
    """The rectangle from blocked cell (r, c) grown right then down, or down then right."""
    h, w = walls.shape
    if first == "right":
        c1 = c
        while c1 + 1 < w and walls[r, c1 + 1]:
            c1 += 1
        r1 = r
        while r1 + 1 < h and walls[r1 + 1, c:c1 + 1].all():
            r1 += 1
    else:
        r1 = r
        while r1 + 1 < h and walls[r1 + 1, c]:
            r1 += 1
        c1 = c
        while c1 + 1 < w and walls[r:r1 + 1, c1 + 1].all():
            c1 += 1
    return r, c, r1, c1


def _grow(walls: np.ndarray, rect: tuple[int, int, int, int], h: int, w: int) -> tuple[int, int, int, int]:
    """``rect`` grown left, up, right and down while a whole blocked column or row borders it."""
    r0, c0, r1, c1 = rect
    grown = True
    while grown:
        grown = False
        if c0 > 0 and walls[r0:r1 + 1, c0 - 1].all():
            c0, grown = c0 - 1, True
        if r0 > 0 and walls[r0 - 1, c0:c1 + 1].all():
            r0, grown = r0 - 1, True
        if c1 + 1 < w and walls[r0:r1 + 1, c1 + 1].all():
            c1, grown = c1 + 1, True
        if r1 + 1 < h and walls[r1 + 1, c0:c1 + 1].all():
            r1, grown = r1 + 1, True
    return r0, c0, r1, c1


def cover_rectangles(walls: torch.Tensor, most: int = OBSTRUCTION_SLOTS) -> torch.Tensor:
    """float32 [B,most,4]: per map of ``walls`` (bool [B,H,W]) rectangles whose union is exactly its
    blocked cells (:func:`cover_cells`), as (top, left, bottom, right) in cell-centre coordinates
    (row - 0.5 .. row + 0.5), on ``walls``' device; unused slots are the empty rectangle far off the
    grid that :func:`~medc_training.envs.tl_sensing.wall_rectangles` leaves there.

    Raises:
        ValueError: ``walls`` is not [B,H,W], ``most`` is not a positive integer, or a map needs more
        than ``most`` rectangles (the message says how many).
    """
    if walls.dim() != 3:
        raise ValueError(f"walls must be bool [B,H,W], got shape {tuple(walls.shape)}")
    if isinstance(most, bool) or not isinstance(most, int) or most < 1:
        raise ValueError(f"most (rectangles per map) must be a positive integer, got {most!r}")
    b = walls.shape[0]
    out = torch.full((b, most, 4), -1e6, dtype=torch.float32)
    out[..., 2:] = -1e6 - 1.0  # empty: bottom < top
    maps = walls.detach().to("cpu", torch.bool).numpy()
    for i in range(b):
        rects = cover_cells(maps[i])
        if len(rects) > most:
            raise ValueError(f"map {i} needs {len(rects)} rectangles to cover its blocked cells, more than "
                             f"the {most} it may have: fewer, or separate, obstructions")
        if rects:
            found = torch.tensor(rects, dtype=torch.float32)
            out[i, :len(rects)] = torch.stack((found[:, 0] - 0.5, found[:, 1] - 0.5,
                                               found[:, 2] + 0.5, found[:, 3] + 0.5), 1)
    return out.to(walls.device)
