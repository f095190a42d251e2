"""Starting a run from a trained bundle (``medc-train --init-from``): the run's network starts as
the bundle's, the run and its bundle record which bundle, a resume from another bundle is refused,
and a bundle of another application, observation or architecture is refused before any training."""

import json

import pytest
import torch
from medc_training.bundle import load_bundle, save_bundle
from medc_training.cli.train import main as train_main
from medc_training.config import TrainConfig
from medc_training.ppo import Trainer
from medc_training.runner import bundle_manifest
from medc_training.warmstart import init_from_bundle

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_steps=16, eval_envs=4, eval_episodes=4,
            total_steps=10**6, arch="mlp", seed=2, lr=1e-3)
CLI = ["--agents", "2", "--walls", "0", "--grid", "6", "--max-steps", "12", "--num-envs", "4",
       "--horizon", "32", "--epochs", "1", "--eval-every", "64", "--eval-episodes", "4",
       "--eval-envs", "4", "--eval-steps", "16", "--arch", "mlp", "--no-tensorboard", "--quiet"]


def _trained_bundle(tmp_path, name="teacher.safetensors", **overrides):
    trainer = Trainer(TrainConfig(**{**TINY, **overrides}))
    trainer.train_update()
    path = save_bundle(tmp_path / name, trainer.net, bundle_manifest(trainer, trainer.cfg, {}))
    return trainer, path


def test_the_run_starts_with_the_bundles_weights_value_head_included(tmp_path):
    teacher, path = _trained_bundle(tmp_path)
    student = Trainer(TrainConfig(**{**TINY, "seed": 5}))
    before = {k: v.clone() for k, v in student.net.state_dict().items()}
    record = init_from_bundle(student, path)
    after = student.net.state_dict()
    for name, tensor in teacher.net.state_dict().items():
        assert torch.equal(after[name], tensor), name
        assert not torch.equal(before[name], tensor), name  # a fresh network differs everywhere
    assert "value.weight" in after
    assert record == {"bundle": "teacher.safetensors", "sha256": load_bundle(path).sha256}
    # The optimiser is fresh: it has taken no step.
    assert not student.optimizer.state


def test_the_run_and_its_bundle_record_the_initial_bundle_and_resume_checks_it(tmp_path):
    _, teacher = _trained_bundle(tmp_path)
    _, other = _trained_bundle(tmp_path, name="other.safetensors", seed=9)
    out = tmp_path / "run"
    assert train_main([*CLI, "--steps", "128", "--out", str(out), "--init-from", str(teacher)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    sha = load_bundle(teacher).sha256
    assert summary["inputs"]["init_from"] == {"bundle": "teacher.safetensors", "sha256": sha}
    assert load_bundle(out / "policy.safetensors").manifest["training"]["init_from"]["sha256"] == sha
    # Carrying the run on from another bundle is another run: refused, naming the field.
    code = train_main([*CLI, "--steps", "256", "--out", str(out), "--init-from", str(other), "--resume"])
    assert code == 2
    assert json.loads((out / "summary.json").read_text())["steps"] == summary["steps"]


def test_resume_names_the_initial_bundle_that_differs(tmp_path, capsys):
    _, teacher = _trained_bundle(tmp_path)
    _, other = _trained_bundle(tmp_path, name="other.safetensors", seed=9)
    out = tmp_path / "run"
    assert train_main([*CLI, "--steps", "128", "--out", str(out), "--init-from", str(teacher)]) == 0
    capsys.readouterr()
    train_main([*CLI, "--steps", "256", "--out", str(out), "--init-from", str(other), "--resume"])
    assert "init_from" in capsys.readouterr().err


@pytest.mark.parametrize("overrides, message", [
    ({"arch": "convnet-small"}, "not this run's network"),
    ({"observation": "maps"}, "observation"),
    ({"env": "fleet_coordination"}, "policy; this run trains"),
])
def test_a_bundle_of_another_kind_is_refused_before_training(tmp_path, overrides, message):
    _, path = _trained_bundle(tmp_path)
    student = Trainer(TrainConfig(**{**TINY, **overrides}))
    before = {k: v.clone() for k, v in student.net.state_dict().items()}
    with pytest.raises(ValueError, match=message):
        init_from_bundle(student, path)
    assert all(torch.equal(before[k], v) for k, v in student.net.state_dict().items())


def test_a_missing_or_tampered_bundle_is_a_clear_error(tmp_path):
    _, path = _trained_bundle(tmp_path)
    student = Trainer(TrainConfig(**TINY))
    with pytest.raises(FileNotFoundError, match="no bundle"):
        init_from_bundle(student, tmp_path / "absent.safetensors")
    data = bytearray(path.read_bytes())
    data[20:28] = b"\xff" * 8
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="not a usable bundle"):
        init_from_bundle(student, bad)


def test_init_from_with_a_sweep_is_refused(tmp_path, capsys):
    _, path = _trained_bundle(tmp_path)
    with pytest.raises(SystemExit):
        train_main([*CLI, "--steps", "128", "--out", str(tmp_path / "s"), "--seeds", "0", "1",
                    "--init-from", str(path)])
    assert "one --seed" in capsys.readouterr().err
