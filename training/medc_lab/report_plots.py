"""The report's figures: several methods' curves with 95% CI bands, and annotated ratio maps
(matplotlib, headless)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from medc_training.stats import curve_band


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


class RatioMap(NamedTuple):
    """One annotated heat map of ratios: ``values[row][column]`` (nan: not run, drawn grey) and
    the text written in each cell."""

    title: str
    xlabel: str
    ylabel: str
    rows: Sequence[str]
    columns: Sequence[str]
    values: Sequence[Sequence[float]]
    texts: Sequence[Sequence[str]]


def plot_ratio_maps(maps: Sequence[RatioMap], png_path: str | Path, title: str, label: str) -> Path:
    """Heat maps of ratios, stacked, on one colour scale: log2 of the ratio, centred on 1 (white), so
    that twice as fast and twice as slow are equally strong colours; ``label`` names the colour bar."""
    logs = [np.log2(np.clip(np.asarray(m.values, dtype=float), 1e-3, 1e3)) for m in maps]
    finite = [abs(x) for a in logs for x in a.ravel() if math.isfinite(x)]
    limit = max([1.0, *finite])
    cmap = plt.get_cmap("RdBu").with_extremes(bad="lightgrey")
    heights = [len(m.rows) + 0.8 for m in maps]
    fig, axes = plt.subplots(len(maps), 1, figsize=(7.2, 1.1 * sum(heights) + 1.0), layout="constrained",
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    image = None
    for ax, m, values in zip(axes[:, 0], maps, logs):
        image = ax.imshow(np.ma.masked_invalid(values), cmap=cmap, vmin=-limit, vmax=limit, aspect="auto")
        for i, row in enumerate(m.texts):
            for j, text in enumerate(row):
                dark = math.isfinite(values[i][j]) and abs(values[i][j]) > 0.6 * limit
                ax.text(j, i, text, ha="center", va="center", fontsize=8, color="white" if dark else "black")
        ax.set_xticks(range(len(m.columns)), m.columns)
        ax.set_yticks(range(len(m.rows)), m.rows)
        ax.set_xlabel(m.xlabel)
        ax.set_ylabel(m.ylabel)
        ax.set_title(m.title, fontsize=9)
    ticks = np.arange(-math.floor(limit), math.floor(limit) + 1)
    bar = fig.colorbar(image, ax=axes[:, 0].tolist(), ticks=ticks)
    bar.ax.set_yticklabels([f"{2.0 ** t:g}×" for t in ticks])
    bar.set_label(label, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return Path(png_path)
