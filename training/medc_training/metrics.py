"""Metrics of a run: one CSV row per evaluation, the same figures in TensorBoard.

TensorBoard tags mean what they mean in CleanRL: ``charts/episodic_return``,
``charts/episodic_length`` and ``charts/success_rate`` are the *training* episodes that finished
since the last log point (sampled actions, exploration included); ``eval/...`` the fixed-episode
evaluation (greedy unless ``eval_greedy`` is off); ``charts/learning_rate``, ``charts/SPS`` (CleanRL's:
environment steps this process has taken over its wall time since training began, evaluations
included); a row with no training episode finished since the last one leaves the training figures
empty (NaN in the CSV, absent in TensorBoard);
``losses/...`` the update's losses and ``losses/explained_variance`` (of the returns by the
value head, CleanRL's formula). The CSV keeps its plain column names (:data:`CSV_COLUMNS`):
``episode_length``/``success_rate`` are the evaluation, ``train_*`` the training episodes.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

CSV_COLUMNS = (
    "step", "update", "episode_length", "success_rate", "train_episode_length", "train_success_rate",
    "expert_follow_rate", "expert_top_rate", "expert_step_fraction", "policy_loss", "value_loss", "entropy",
    "approx_kl", "clipfrac", "bc_loss", "sps", "wall_time",
    # Added later; appended so that older CSVs keep their column order.
    "episode_return", "train_episode_return", "learning_rate", "explained_variance",
)

TB_NAMES = {
    # Evaluation (fixed episodes, greedy by default).
    "episode_length": "eval/episodic_length",
    "success_rate": "eval/success_rate",
    "episode_return": "eval/episodic_return",
    # Training episodes (CleanRL's charts/episodic_*).
    "train_episode_length": "charts/episodic_length",
    "train_success_rate": "charts/success_rate",
    "train_episode_return": "charts/episodic_return",
    "learning_rate": "charts/learning_rate",
    "expert_follow_rate": "charts/expert_follow_rate",
    "expert_top_rate": "charts/expert_top_rate",
    "expert_step_fraction": "charts/expert_step_fraction",
    "policy_loss": "losses/policy_loss",
    "value_loss": "losses/value_loss",
    "entropy": "losses/entropy",
    "approx_kl": "losses/approx_kl",
    "clipfrac": "losses/clipfrac",
    "bc_loss": "losses/bc_loss",
    "explained_variance": "losses/explained_variance",
    "sps": "charts/SPS",
}


def read_metrics(path: str | Path) -> list[dict]:
    """Rows of a metrics CSV as dicts of floats (empty cells become NaN). Every NaN is
    ``math.nan`` itself, so two rows with NaN in the same cells compare equal."""
    def value(v: str | None) -> float:
        x = float(v) if v not in ("", None) else math.nan
        return math.nan if x != x else x

    with open(path, newline="") as f:
        return [{k: value(v) for k, v in row.items()} for row in csv.DictReader(f)]


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
