"""medc-inspect --export: the ONNX / TorchScript model computes what the bundle computes on real
observations (same greedy actions, logits within 1e-4), and its contract JSON matches the manifest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from medc_training.bundle import load_bundle
from medc_training.cli.inspect import main as inspect_main

TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"


def real_observations(bundle, envs: int = 16, steps: int = 6) -> np.ndarray:
    """Observations [M, C, H, W] of the shipped team's scenario, along a few random-move steps."""
    from medc_training.envs import make_batched

    env = bundle.manifest["environment"]
    core = make_batched("target_localization", envs, seed=3, agents=env["agents"], walls=env["walls"],
                        grid=env["grid"], observation=bundle.observation)
    obs, _ = core.reset()
    batches = [obs]
    gen = torch.Generator().manual_seed(0)
    for _ in range(steps):
        actions = torch.randint(0, bundle.num_actions, (envs, env["agents"]), generator=gen)
        obs = core.step(actions).obs
        batches.append(obs.clone())
    return torch.cat([b.reshape(-1, *bundle.obs_shape) for b in batches]).numpy().astype(np.float32)


@pytest.fixture(scope="module")
def team():
    bundle = load_bundle(TEAM)
    obs = real_observations(bundle)
    with torch.no_grad():
        logits, _ = bundle.net(torch.from_numpy(obs))
    return bundle, obs, logits.numpy()


def test_onnx_export_gives_the_bundles_actions(team, tmp_path, capsys):
    ort = pytest.importorskip("onnxruntime")
    bundle, obs, logits = team
    out = tmp_path / "team.onnx"
    assert inspect_main(["--export", "onnx", str(TEAM), str(out)]) == 0
    assert "team.onnx.json" in capsys.readouterr().out
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got, value = session.run(["logits", "value"], {"obs": obs})
    assert got.shape == logits.shape and value.shape == (len(obs),)
    assert np.abs(got - logits).max() < 1e-4
    assert (got.argmax(-1) == bundle.act(obs).numpy()).all()
    side = json.loads((tmp_path / "team.onnx.json").read_text())
    assert side["actions"] == bundle.action_names and side["model_file"] == "team.onnx"
    assert side["inputs"]["obs"]["shape"] == ["batch", *bundle.obs_shape]
    assert side["inputs"]["obs"]["observation"] == bundle.observation
    assert side["source_bundle_sha256"] == bundle.sha256


def test_torchscript_export_gives_the_bundles_actions(team, tmp_path):
    bundle, obs, logits = team
    out = tmp_path / "team.pt"
    assert inspect_main(["--export", "torchscript", str(TEAM), str(out)]) == 0
    model = torch.jit.load(str(out))
    with torch.no_grad():
        got, _ = model(torch.from_numpy(obs))
    assert np.abs(got.numpy() - logits).max() < 1e-4
    assert (got.argmax(-1) == bundle.act(obs)).all()
    assert json.loads((tmp_path / "team.pt.json").read_text())["model_format"] == "torchscript"


def test_export_refuses_bad_input_without_a_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a bundle")
    assert inspect_main(["--export", "onnx", str(bad), str(tmp_path / "x.onnx")]) == 1
    err = capsys.readouterr().err
    assert "medc-inspect:" in err and "Traceback" not in err and not (tmp_path / "x.onnx").exists()
    with pytest.raises(SystemExit) as exit_:
        inspect_main(["--export", "onnx", str(TEAM)])  # no OUT
    assert exit_.value.code == 2
