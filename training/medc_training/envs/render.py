"""Pictures of the environments: the area (paper Fig. 5a) and an agent's observation maps (Fig. 5b-f).

:func:`render_frame` draws from the observation maps of all agents (plus, for target
localization, the target cell, which no agent observes), so the ParallelEnv can draw the
last state of an episode even after the batched core has moved on. Drawing is plain numpy;
:func:`save_observation_png` uses matplotlib's object API (no global pyplot state).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

#: Channel names per application, in observation order.
CHANNEL_NAMES: dict[str, tuple[str, ...]] = {
    "target_localization": ("Location", "Team locations", "Readings", "Visit counts", "Walls"),
    "fleet_coordination": (
        "Location",
        "Team locations",
        "Waiting customers",
        "Their destinations",
        "Own passengers' destinations",
        "Own load",
    ),
    "maze_cleaning": ("Location", "Team locations", "Dirty cells", "Walls"),
}

_AGENT_COLOURS = np.array(
    [(31, 119, 180), (44, 160, 44), (148, 103, 189), (255, 127, 14), (23, 190, 207), (227, 119, 194)],
    dtype=np.uint8,
)
_WALL = (60, 60, 60)
_GRID_LINE = (215, 215, 215)


def _disc(px: int, frac: float) -> np.ndarray:
    yy, xx = np.mgrid[0:px, 0:px] + 0.5
    return (yy - px / 2) ** 2 + (xx - px / 2) ** 2 <= (frac * px / 2) ** 2


def _agent_cells(obs: np.ndarray) -> list[tuple[int, int]]:
    w = obs.shape[-1]
    return [divmod(int(np.argmax(obs[i, 0])), w) for i in range(obs.shape[0])]


def render_frame(
    name: str, obs: torch.Tensor | np.ndarray, extras: dict[str, Any] | None = None, cell_px: int = 16
) -> np.ndarray:
    """uint8 [H*cell_px, W*cell_px, 3] picture of one environment.

    name:   application (one of ENV_NAMES).
    obs:    float [N,C,H,W] every agent's observation maps.
    extras: e.g. {"target": (row, col)} for target localization.
    """
    if name not in CHANNEL_NAMES:
        raise ValueError(f"unknown environment {name!r}; choose one of {', '.join(CHANNEL_NAMES)}")
    obs = obs.detach().cpu().numpy() if isinstance(obs, torch.Tensor) else np.asarray(obs)
    extras = extras or {}
    h, w = obs.shape[-2:]
    cells = np.full((h, w, 3), 255.0)
    if name == "target_localization":
        readings, walls = obs[0, 2], obs[0, 4] > 0.5
        visited = readings > 0
        # Visited cells from pale yellow (weak reading) to red (strong), as a heat map.
        ramp = np.stack([np.full_like(readings, 255.0), 230 * (1 - readings), 120 * (1 - readings)], -1)
        cells[visited] = ramp[visited]
        cells[walls] = _WALL
    elif name == "fleet_coordination":
        cells[obs[0, 3] > 0] = (200, 235, 200)
        cells[obs[0, 2] > 0] = (255, 200, 120)
    else:
        cells[obs[0, 2] > 0] = (205, 180, 140)
        cells[obs[0, 3] > 0.5] = _WALL
    img = np.repeat(np.repeat(cells.astype(np.uint8), cell_px, 0), cell_px, 1)
    img[::cell_px, :] = _GRID_LINE
    img[:, ::cell_px] = _GRID_LINE
    if name == "fleet_coordination":
        # Destinations of waiting customers: a small green square; pick-ups: a larger orange one.
        q = cell_px // 3
        for r, c in zip(*np.nonzero(obs[0, 3] > 0)):
            y, x = r * cell_px, c * cell_px
            img[y + q : y + cell_px - q, x + q : x + cell_px - q] = (0, 140, 0)
    if "target" in extras:
        r, c = extras["target"]
        star = _disc(cell_px, 0.9)
        img[r * cell_px : (r + 1) * cell_px, c * cell_px : (c + 1) * cell_px][star] = (200, 0, 0)
    ring, disc = _disc(cell_px, 0.8), _disc(cell_px, 0.6)
    for i, (r, c) in enumerate(_agent_cells(obs)):
        block = img[r * cell_px : (r + 1) * cell_px, c * cell_px : (c + 1) * cell_px]
        block[ring] = (0, 0, 0)
        block[disc] = _AGENT_COLOURS[i % len(_AGENT_COLOURS)]
    return img


def save_observation_png(
    obs: torch.Tensor | np.ndarray,
    path: str | Path,
    application: str = "target_localization",
    title: str | None = None,
    channel_names: tuple[str, ...] | list[str] | None = None,
) -> Path:
    """Write one agent's observation maps (float [C,H,W]) side by side as one PNG (Fig. 5b-f).

    ``channel_names``: titles of the C maps (default: the application's paper maps; give the
    observation's own, e.g. ``env.observation_channels``, for other target-localization variants).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if application not in CHANNEL_NAMES:
        raise ValueError(f"unknown environment {application!r}; choose one of {', '.join(CHANNEL_NAMES)}")
    obs = obs.detach().cpu().numpy() if isinstance(obs, torch.Tensor) else np.asarray(obs)
    names = (tuple(n.replace("_", " ").capitalize() for n in channel_names) if channel_names
             else CHANNEL_NAMES[application])
    if obs.ndim != 3 or obs.shape[0] != len(names):
        raise ValueError(f"obs must be one agent's maps [C,H,W] with C={len(names)}, got shape {obs.shape}")
    fig = Figure(figsize=(2.6 * len(names), 3.0))
    FigureCanvasAgg(fig)
    for k, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), k + 1)
        ax.imshow(obs[k], cmap="viridis", vmin=0.0, vmax=1.0, interpolation="nearest")
        ax.set_title(f"({chr(ord('b') + k)}) {name}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def save_frame_png(frame: np.ndarray, path: str | Path) -> Path:
    """Write an RGB frame from :func:`render_frame` as a PNG."""
    from matplotlib.image import imsave

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imsave(path, frame)
    return path
