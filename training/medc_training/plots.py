"""A run's learning curve as a figure (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from .metrics import read_metrics


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
