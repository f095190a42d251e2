"""Learning-curve figures (matplotlib, headless)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .metrics import read_metrics
from .stats import curve_band


def plot_learning_curve(csv_path: str | Path, png_path: str | Path, title: str = "",
                        greedy: bool = True) -> Path:
    """One run's evaluation episode length (and success rate) against training steps."""
    rows = read_metrics(csv_path)
    steps = [r["step"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, [r["episode_length"] for r in rows],
            label=f"episode length ({'greedy' if greedy else 'sampled'} eval)")
    ax.set_xlabel("training steps")
    ax.set_ylabel("mean episode length")
    ax2 = ax.twinx()
    ax2.plot(steps, [r["success_rate"] for r in rows], color="tab:green", alpha=0.6, label="success rate")
    ax2.set_ylabel("success rate")
    ax2.set_ylim(0, 1.05)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return Path(png_path)


def plot_methods(series: dict[str, tuple[Sequence[float], Sequence[Sequence[float]]]], png_path: str | Path,
                 title: str, ylabel: str = "mean episode length (greedy eval)",
                 references: dict[str, tuple[float, float]] | None = None) -> Path:
    """Several methods' mean curves over seeds with 95% CI bands.

    ``series`` maps a label to (steps, [curve per seed]); ``references`` a label to (mean, 95% CI
    half-width) of a fixed policy (a classical controller), drawn as a dashed line with its band.
    """
    fig, ax = plt.subplots(figsize=(6.4, 4))
    for label, (steps, curves) in series.items():
        n = min(len(c) for c in curves)
        mean, half = curve_band([c[:n] for c in curves])
        x = np.asarray(steps[:n])
        ax.plot(x, mean, label=f"{label} (n={len(curves)})")
        ax.fill_between(x, mean - half, mean + half, alpha=0.2)
    for i, (label, (mean, half)) in enumerate((references or {}).items()):
        color = f"C{(len(series) + i) % 10}"
        ax.axhline(mean, linestyle="--", linewidth=1.0, color=color, label=label)
        ax.axhspan(mean - half, mean + half, color=color, alpha=0.08)
    ax.set_xlabel("training steps")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return Path(png_path)
