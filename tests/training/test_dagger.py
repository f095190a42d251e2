"""DAgger cloning of the oracle (medc_training.dagger, medc-clone): labels, loss, dataset, a run."""

import json
import math

import pytest
import torch
from medc_training.bundle import load_bundle
from medc_training.cli import clone as clone_cli
from medc_training.dagger import CloneConfig, _Dataset, best_moves, clone_loss, clone_oracle


def test_best_moves_keeps_ties_and_drops_masked_moves():
    mask = torch.tensor([[True, True, False, True], [True, False, False, False]])
    scores = torch.tensor([[-2.0, -1.0, 0.0, -1.0], [-5.0, -1.0, -1.0, -1.0]])
    assert best_moves(mask, scores).tolist() == [[False, True, False, True], [True, False, False, False]]


def test_clone_loss_is_cross_entropy_against_the_best_set():
    # Uniform logits over 4 valid moves (one of 5 masked): each valid move has probability 1/4,
    # so the cross-entropy against any subset of best moves is log 4.
    logits = torch.zeros(1, 5)
    mask = torch.tensor([[True, True, True, True, False]])
    best = torch.tensor([[True, False, True, False, False]])
    assert clone_loss(logits, mask, best).item() == pytest.approx(math.log(4))
    # Two best moves with probabilities p1, p2: the loss is -(log p1 + log p2) / 2.
    logits = torch.tensor([[2.0, 0.0, 1.0, 0.0, 50.0]])
    p = torch.softmax(logits[0, :4], -1)
    want = -(math.log(p[0]) + math.log(p[2])) / 2
    assert clone_loss(logits, mask, best).item() == pytest.approx(want, rel=1e-5)


def test_clone_loss_gradient_moves_probability_to_the_best_moves():
    logits = torch.zeros(1, 4, requires_grad=True)
    mask = torch.ones(1, 4, dtype=torch.bool)
    best = torch.tensor([[False, True, False, False]])
    clone_loss(logits, mask, best).backward()
    assert logits.grad[0, 1] < 0 and (logits.grad[0, [0, 2, 3]] > 0).all()


def test_dataset_keeps_the_newest_samples_up_to_its_cap():
    data = _Dataset((1, 1, 1), 2, cap=5, device=torch.device("cpu"))
    for start in (0, 3, 6):
        obs = torch.arange(start, start + 3, dtype=torch.float32).view(3, 1, 1, 1) / 16
        data.add(obs, torch.ones(3, 2, dtype=torch.bool), torch.zeros(3, 2, dtype=torch.bool))
    assert data.size == 5
    kept = sorted((data.obs.view(-1).float() * 16).round().int().tolist())
    assert kept == [4, 5, 6, 7, 8]
    data.add(
        torch.arange(7, dtype=torch.float32).view(7, 1, 1, 1) / 16,
        torch.ones(7, 2, dtype=torch.bool),
        torch.zeros(7, 2, dtype=torch.bool),
    )  # larger than the cap: only its last 5 stay
    assert sorted((data.obs.view(-1).float() * 16).round().int().tolist()) == [2, 3, 4, 5, 6]


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="beta_decay"):
        CloneConfig(beta_decay=1.5).validate()
    with pytest.raises(ValueError, match="num_envs"):
        CloneConfig(num_envs=0).validate()
    assert CloneConfig(total_steps=6401, num_envs=64, rollout_len=100).iterations == 2


def test_clone_beats_a_random_team_and_ships_a_bundle(tmp_path):
    torch.set_num_threads(1)
    cfg = CloneConfig(
        agents=3,
        walls=0,
        grid=7,
        max_steps=20,
        arch="convnet-small",
        total_steps=16 * 40 * 6,
        num_envs=16,
        rollout_len=40,
        grad_steps=150,
        eval_episodes=96,
        eval_envs=16,
        eval_every=4 * 16 * 40,  # training steps: every 4th iteration
        seed=3,
    )
    summary = clone_oracle(cfg, tmp_path / "run", bundle_to=tmp_path / "expert.safetensors")
    m = summary["metrics"]
    assert summary["iterations"] == 6 and summary["steps"] == 16 * 40 * 6
    # Three readings locate the source; a random team needs ~13 of 20 steps (seeds 3, 4, on 96
    # fixed episodes: greedy clone 2.1 and 2.1 steps against random 13.2 and 12.9).
    assert m["greedy_episode_length"] < m["random_episode_length"] - 2, m
    assert m["greedy_success_rate"] > m["random_success_rate"], m
    rows = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["3", "5"]  # every 4th iteration and the last
    bundle = load_bundle(tmp_path / "expert.safetensors")
    assert bundle.manifest["training"]["method"] == "dagger"
    assert bundle.manifest["training"]["evaluation"] == {"evaluator": "episodes", "episodes": 96, "envs": 16,
                                                         "greedy": True}
    assert bundle.manifest["environment"] == {"agents": 3, "grid": 7, "max_steps": 20, "walls": 0}
    assert bundle.manifest["metrics"]["greedy_episode_length"] == pytest.approx(m["greedy_episode_length"])
    assert (tmp_path / "run" / "learning_curve.png").stat().st_size > 1000


def test_cli_runs_and_rejects_bad_options(tmp_path, capsys):
    assert (
        clone_cli.main(
            [
                "--env",
                "maze_cleaning",
                "--agents",
                "1",
                "--grid",
                "6",
                "--max-steps",
                "60",
                "--env-option",
                "complexity=0.5",
                "--eval-sampled",
                "--arch",
                "mlp",
                "--steps",
                "256",
                "--num-envs",
                "8",
                "--rollout-len",
                "16",
                "--grad-steps",
                "5",
                "--eval-episodes",
                "8",
                "--out",
                str(tmp_path / "c"),
                "--quiet",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["iterations"] == 2 and out["steps"] == 256
    manifest = load_bundle(tmp_path / "c" / "policy.safetensors").manifest
    assert manifest["environment"]["complexity"] == 0.5
    # A folder holds one cloning run: a second one there needs --overwrite.
    before = (tmp_path / "c" / "summary.json").read_text()
    assert clone_cli.main(["--out", str(tmp_path / "c"), "--quiet", "--steps", "64"]) == 2
    assert "already holds a cloning run" in capsys.readouterr().err
    assert (tmp_path / "c" / "summary.json").read_text() == before
    assert clone_cli.main(["--env-option", "customers=many", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "KEY=NUMBER" in capsys.readouterr().err
    assert clone_cli.main(["--beta-decay", "2", "--out", str(tmp_path / "y"), "--quiet"]) == 2
    assert "beta_decay" in capsys.readouterr().err


def test_eval_every_counts_training_steps_as_in_medc_train(tmp_path):
    """One meaning of eval_every (and --eval-every) in TrainConfig and CloneConfig: training steps.
    A default 128,000-step clone, as the reproduction plans its experts, evaluates after every 4th
    iteration of 6,400 steps and after the last, as when the field counted iterations."""
    from pathlib import Path

    from medc_lab.plan import Plan
    from medc_training.config import RunConfig, TrainConfig

    shared = {f for f in RunConfig.__dataclass_fields__}
    assert shared <= set(TrainConfig.__dataclass_fields__) and shared <= set(CloneConfig.__dataclass_fields__)
    default = CloneConfig(total_steps=128_000)
    assert default.evaluation_points() == [25_600, 51_200, 76_800, 102_400, 128_000]
    assert CloneConfig(total_steps=70_000, eval_every=30_000).evaluation_points() == [32_000, 64_000, 70_400]
    assert CloneConfig(total_steps=12_800, eval_every=1).evaluation_points() == [6_400, 12_800]
    experts = Plan("cpu", 1, tmp_path / "out", Path("models")).expert_jobs(retrain=True)
    assert experts and all(CloneConfig.from_dict(j["config"]).evaluation_points()
                           == default.evaluation_points() for j in experts)
    args = clone_cli.build_parser().parse_args(["--out", "x", "--eval-every", "12800", "--threads", "1"])
    cfg = clone_cli.config_from_args(args)
    assert (cfg.eval_every, cfg.torch_threads) == (12_800, 1)
    assert cfg.evaluation_points()[:2] == [12_800, 25_600]


def test_a_clone_config_recorded_when_eval_every_counted_iterations_keeps_its_evaluation_points():
    """Every committed DAgger summary (docs/reproduction) was written when eval_every counted
    iterations: read today, its config evaluates at the steps its metrics.csv rows were written."""
    import csv
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "docs" / "reproduction"
    checked = 0
    for summary in sorted(root.rglob("summary.json")):
        recorded = json.loads(summary.read_text()).get("config", {})
        if "rollout_len" not in recorded or (summary.parent / "metrics.csv").exists() is False:
            continue
        assert "torch_threads" not in recorded and recorded["eval_every"] < 100, summary
        cfg = CloneConfig.from_dict(recorded).validate()
        assert cfg.eval_every == recorded["eval_every"] * recorded["num_envs"] * recorded["rollout_len"]
        with open(summary.parent / "metrics.csv") as f:
            steps = [int(row["step"]) for row in csv.DictReader(f)]
        assert cfg.evaluation_points() == steps, summary
        checked += 1
    assert checked >= 20
    # Written today, a config reads back as it is (no conversion), and unknown fields are refused.
    today = CloneConfig(eval_every=12_800)
    assert CloneConfig.from_dict(today.to_dict()) == today
    with pytest.raises(ValueError, match="unknown config fields"):
        CloneConfig.from_dict({**today.to_dict(), "horizon": 4000})
