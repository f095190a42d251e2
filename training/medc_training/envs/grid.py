"""Grid helpers shared by the three applications: the 8 moves, masks, batched BFS, sampling.

Cells are (row, col) with row 0 at the top (north). Every function works on batched torch
tensors on any device and contains no Python loop over the batch.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

#: The 8 one-cell moves, in action-index order: N, NE, E, SE, S, SW, W, NW, as (drow, dcol).
ACTIONS: tuple[tuple[int, int], ...] = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1))
ACTION_NAMES: tuple[str, ...] = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")
#: OPPOSITE[a] is the move in the opposite direction: (a + 4) % 8.
OPPOSITE: tuple[int, ...] = tuple((a + 4) % 8 for a in range(8))

_DELTA_CACHE: dict[torch.device, torch.Tensor] = {}


def action_deltas(device: torch.device | str) -> torch.Tensor:
    """int64 [8,2] (drow, dcol) of each move on ``device`` (cached)."""
    device = torch.device(device)
    if device not in _DELTA_CACHE:
        _DELTA_CACHE[device] = torch.tensor(ACTIONS, dtype=torch.long, device=device)
    return _DELTA_CACHE[device]


def grid_cells(grid: int, device: torch.device | str) -> torch.Tensor:
    """int64 [G²,2]: the (row, col) of every cell of a ``grid`` x ``grid`` area, in row-major order."""
    idx = torch.arange(grid * grid, device=device)
    return torch.stack((idx // grid, idx % grid), dim=-1)


def pad_blocked(walls: torch.Tensor) -> torch.Tensor:
    """bool [B,H+2,W+2]: ``walls`` with a one-cell blocked border (off-grid counts as wall)."""
    return F.pad(walls, (1, 1, 1, 1), value=True)


def neighbour_index(positions: torch.Tensor, width: int, deltas: torch.Tensor) -> torch.Tensor:
    """int64 [B,N,A]: flat index, in a grid padded by one cell, of each agent's cell after each move.

    ``width`` is the unpadded grid width; ``positions`` int64 [B,N,2] (row, col).
    """
    rows = positions[..., 0:1] + 1 + deltas[:, 0]
    cols = positions[..., 1:2] + 1 + deltas[:, 1]
    return rows * (width + 2) + cols


def move_mask(positions: torch.Tensor, blocked_padded: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """bool [B,N,A]: True where the move lands on an in-grid free cell.

    ``blocked_padded`` bool [B,H+2,W+2] from :func:`pad_blocked`.
    """
    b, n = positions.shape[:2]
    width = blocked_padded.shape[-1] - 2
    idx = neighbour_index(positions, width, deltas).view(b, -1)
    return ~blocked_padded.view(b, -1).gather(1, idx).view(b, n, -1)


def gather_cells(grid: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """grid [B,H,W], positions int64 [B,N,2] -> grid values at the positions, [B,N]."""
    b = positions.shape[0]
    width = grid.shape[-1]
    idx = positions[..., 0] * width + positions[..., 1]
    return grid.reshape(b, -1).gather(1, idx)


def bfs_distance(free: torch.Tensor, sources: torch.Tensor, check_every: int = 4) -> torch.Tensor:
    """Batched breadth-first search over 8-connected grids.

    free:    bool [B,H,W] cells an agent may stand on.
    sources: bool [B,H,W] start cells (distance 0).
    Returns float32 [B,H,W]: number of one-cell moves (8 directions, only through free cells)
    from the nearest source; ``inf`` for walls and unreachable cells.

    Each wave is a 3x3 dilation of the reached set (two passes of shifted ORs over the
    whole batch), so the cost grows with the longest distance, not with the batch size.
    """
    k, h, w = free.shape
    start = sources & free
    reached = F.pad(start, (1, 1, 1, 1))  # the padding stays False: nothing is reached off-grid
    inner = reached[:, 1:-1, 1:-1]
    dist = torch.full((k, h, w), float("inf"), device=free.device).masked_fill_(start, 0.0)
    step = 0
    while True:
        step += 1
        rows = reached[:, :, :-2] | reached[:, :, 1:-1] | reached[:, :, 2:]
        grown = (rows[:, :-2] | rows[:, 1:-1] | rows[:, 2:]) & free
        new = grown & ~inner
        dist.masked_fill_(new, float(step))
        inner.copy_(grown)
        if step % check_every == 0 and not bool(new.any()):
            return dist


def agent_windows(maps: torch.Tensor, positions: torch.Tensor, radius: int,
                  outside: torch.Tensor | None = None) -> torch.Tensor:
    """Agent-centred windows of every agent's own maps: float32 [B,N,C,2r+1,2r+1].

    maps float [B,N,C,G,G]; positions int64 [B,N,2]; ``outside`` float [C]: the value each channel
    takes on cells off the grid (default 0). Agent i's window has its own cell at the centre.
    """
    b, n, c, g, _ = maps.shape
    side = 2 * int(radius) + 1
    win = team_windows(maps.reshape(b * n, c, g, g), positions.reshape(b * n, 1, 2), radius, outside)
    return win.view(b, n, c, side, side)


def team_windows(maps: torch.Tensor | Sequence[torch.Tensor], positions: torch.Tensor, radius: int,
                 outside: torch.Tensor | None = None, out: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`agent_windows` of maps the whole team shares: float32 [B,N,C,2r+1,2r+1] from maps
    float [B,C,G,G] (or a sequence of C maps [B,G,G]), equal to
    ``agent_windows(maps.unsqueeze(1).expand(B, N, C, G, G), ...)``.

    Each window cell is gathered from its grid cell, clamped onto the grid, and cells off the grid
    then take ``outside``: O(B·N·C·(2r+1)²) per call, nothing padded or stacked. ``out``: an
    optional float32 [B,N,C,2r+1,2r+1] tensor to write into.
    """
    layers = list(maps.unbind(1)) if isinstance(maps, torch.Tensor) else list(maps)
    b, g = layers[0].shape[0], layers[0].shape[-1]
    n, c = positions.shape[1], len(layers)
    r, side = int(radius), 2 * int(radius) + 1
    offs = torch.arange(-r, r + 1, device=positions.device)
    rows = positions[..., 0:1] + offs  # [B,N,side]
    cols = positions[..., 1:2] + offs
    off_grid = ((rows < 0) | (rows >= g)).unsqueeze(-1) | ((cols < 0) | (cols >= g)).unsqueeze(-2)
    idx = (rows.clamp(0, g - 1).unsqueeze(-1) * g + cols.clamp(0, g - 1).unsqueeze(-2)).view(b, -1)
    if out is None:
        out = torch.empty((b, n, c, side, side), dtype=torch.float32, device=positions.device)
    fill = torch.zeros(c) if outside is None else outside.to("cpu", torch.float32)
    for i, layer in enumerate(layers):
        out[:, :, i] = layer.reshape(b, g * g).gather(1, idx).view(b, n, side, side)
        out[:, :, i].masked_fill_(off_grid, float(fill[i]))
    return out


def random_free_cells(free: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """int64 [B,count,2]: ``count`` distinct free cells per grid, uniformly at random.

    ``free`` bool [B,H,W]; every grid must have at least ``count`` free cells.
    """
    b, h, w = free.shape
    scores = torch.rand((b, h * w), generator=generator, device=free.device)
    scores = scores.masked_fill(~free.view(b, -1), -1.0)
    idx = scores.topk(count, dim=1).indices
    return torch.stack((idx // w, idx % w), dim=-1)
