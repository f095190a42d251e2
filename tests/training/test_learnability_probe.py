"""scripts/learnability_probe.py: the supervised probe runs end to end and its scoring is right."""

import importlib.util
import json
from pathlib import Path

import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "learnability_probe.py"


def _probe():
    spec = importlib.util.spec_from_file_location("learnability_probe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_best_moves_counts_ties_and_ignores_masked_moves():
    probe = _probe()
    mask = torch.tensor([[True, True, False, True]])
    scores = torch.tensor([[1.0, 3.0, 9.0, 3.0]])  # the 9 is masked out; 1 and 3 tie for best
    assert probe.best_moves(mask, scores).tolist() == [[False, True, False, True]]


def test_probe_runs_and_reports_accuracies(capsys):
    probe = _probe()
    assert probe.main(["--grid", "6", "--walls", "0", "--train-steps", "16", "--envs", "4",
                       "--iterations", "8", "--arch", "mlp"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["samples"] == 16 * 4
    assert 0.0 < result["random_move_accuracy"] < 1.0
    assert 0.0 <= result["held_out_accuracy"]["mlp"] <= 1.0
