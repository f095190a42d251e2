"""Metrics of a run: one CSV row per evaluation, the same figures in TensorBoard.

TensorBoard names are namespaced CleanRL-style (``charts/episodic_length``,
``losses/approx_kl``); the CSV uses the plain column names in :data:`CSV_COLUMNS`.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

CSV_COLUMNS = (
    "step", "update", "episode_length", "success_rate", "train_episode_length", "train_success_rate",
    "expert_follow_rate", "expert_top_rate", "expert_step_fraction", "policy_loss", "value_loss", "entropy",
    "approx_kl", "clipfrac", "bc_loss", "sps", "wall_time",
)

TB_NAMES = {
    "episode_length": "charts/episodic_length",
    "success_rate": "charts/success_rate",
    "train_episode_length": "charts/train_episodic_length",
    "train_success_rate": "charts/train_success_rate",
    "expert_follow_rate": "charts/expert_follow_rate",
    "expert_top_rate": "charts/expert_top_rate",
    "expert_step_fraction": "charts/expert_step_fraction",
    "policy_loss": "losses/policy_loss",
    "value_loss": "losses/value_loss",
    "entropy": "losses/entropy",
    "approx_kl": "losses/approx_kl",
    "clipfrac": "losses/clipfrac",
    "bc_loss": "losses/bc_loss",
    "sps": "charts/SPS",
}


def read_metrics(path: str | Path) -> list[dict]:
    """Rows of a metrics CSV as dicts of floats (empty cells become NaN)."""
    with open(path, newline="") as f:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in row.items()}
                for row in csv.DictReader(f)]


class MetricsLogger:
    """Appends rows to ``metrics.csv`` and scalars to TensorBoard under ``out_dir``.

    On resume (``resume_from_step`` given) rows logged at or after the checkpoint's step
    are dropped (the evaluation at that step runs again after the checkpoint is loaded),
    so a killed-and-resumed run's CSV has each step once.
    """

    def __init__(self, out_dir: str | Path, tensorboard: bool = True,
                 resume_from_step: int | None = None, csv_name: str = "metrics.csv") -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = self.out_dir / csv_name
        if resume_from_step is not None and self.csv_path.exists():
            kept = [r for r in self._raw_rows() if int(float(r["step"])) < resume_from_step]
            self._write_rows(kept)
        elif not self.csv_path.exists() or resume_from_step is None:
            self._write_rows([])
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.out_dir / "tb"), purge_step=resume_from_step)

    def _raw_rows(self) -> list[dict]:
        with open(self.csv_path, newline="") as f:
            return list(csv.DictReader(f))

    def _write_rows(self, rows: list[dict]) -> None:
        with open(self.csv_path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
            w.writeheader()
            w.writerows(rows)

    def log(self, row: dict) -> None:
        """Append one row (missing columns are left empty) and mirror it to TensorBoard."""
        clean = {k: row.get(k, "") for k in CSV_COLUMNS}
        with open(self.csv_path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=CSV_COLUMNS).writerow(clean)
        if self.writer is not None:
            step = int(row["step"])
            for key, name in TB_NAMES.items():
                value = row.get(key)
                if isinstance(value, int | float) and not math.isnan(float(value)):
                    self.writer.add_scalar(name, float(value), step)
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
