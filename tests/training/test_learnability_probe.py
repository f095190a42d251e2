"""The learnability probe (medc_lab.probes.learnability): it runs end to end and its scoring is right."""

import json

import torch
from medc_lab.cli import learnability_probe
from medc_lab.probes import learnability


def test_best_moves_counts_ties_and_ignores_masked_moves():
    mask = torch.tensor([[True, True, False, True]])
    scores = torch.tensor([[1.0, 3.0, 9.0, 3.0]])  # the 9 is masked out; 1 and 3 tie for best
    assert learnability.best_moves(mask, scores).tolist() == [[False, True, False, True]]


def test_probe_runs_and_reports_accuracies(capsys):
    assert learnability_probe.main(["--grid", "6", "--walls", "0", "--train-steps", "16", "--envs", "4",
                                     "--iterations", "8", "--arch", "mlp"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["samples"] == 16 * 4
    assert 0.0 < result["random_move_accuracy"] < 1.0
    assert 0.0 <= result["held_out_accuracy"]["mlp"] <= 1.0
