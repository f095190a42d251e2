"""medc-inspect: prints a valid bundle's manifest, exits non-zero with the reason otherwise."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest
import torch
from bundle_forge import MANIFEST, forge, valid_parts
from medc_training.bundle import read_manifest, save_bundle
from medc_training.cli.inspect import main
from medc_training.nets import make_actor_critic


@pytest.fixture(scope="module")
def bundle_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("inspect") / "expert.safetensors"
    return save_bundle(path, make_actor_critic("convnet-small", (5, 10, 10), 8), MANIFEST)


def test_readable_summary_of_a_valid_bundle(bundle_path, capsys) -> None:
    assert main([str(bundle_path)]) == 0
    out = capsys.readouterr().out
    assert "target_localization" in out
    assert "5 x 10 x 10 (own_location, team_locations, readings, visit_counts, walls)" in out
    assert "8 (N, NE, E, SE, S, SW, W, NW)" in out
    assert "convnet-small" in out and "conv2d 3x3 -> 16" in out
    params = sum(p.numel() for p in make_actor_critic("convnet-small", (5, 10, 10), 8).parameters())
    assert f"{params:,} parameters" in out
    assert "mean_episode_length  41.5" in out and "method" in out


def test_json_output_is_the_manifest(bundle_path, capsys) -> None:
    assert main(["--json", str(bundle_path)]) == 0
    assert json.loads(capsys.readouterr().out) == read_manifest(bundle_path)


def test_manifest_only_mode_skips_weight_decoding(tmp_path, capsys) -> None:
    tensors, manifest = valid_parts("mlp")
    poisoned = tensors["policy.weight"].clone()
    poisoned[0, 0] = float("nan")
    path = tmp_path / "nan.safetensors"
    path.write_bytes(forge({**tensors, "policy.weight": poisoned}, manifest))
    assert main(["--manifest-only", str(path)]) == 0  # header and manifest are fine...
    capsys.readouterr()
    assert main([str(path)]) == 1  # ...but the weights are not
    assert "contains NaN or infinite values" in capsys.readouterr().err


@pytest.mark.parametrize(("content", "reason"), [
    (b"", "too short"),
    (b"hello, world, not a model file", "over the"),
    (None, "unknown layer type"),
])
def test_invalid_files_exit_1_with_the_reason(tmp_path, capsys, content, reason) -> None:
    if content is None:
        tensors, manifest = valid_parts("mlp")
        manifest["architecture"]["layers"][0] = {"type": "exec"}
        content = forge(tensors, manifest)
    path = tmp_path / "bad.safetensors"
    path.write_bytes(content)
    assert main([str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("medc-inspect: invalid bundle:") and reason in captured.err


def test_missing_file_and_bad_usage(tmp_path, capsys) -> None:
    assert main([str(tmp_path / "nope.safetensors")]) == 1
    assert "no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2


def test_console_script_is_installed(bundle_path, tmp_path) -> None:
    exe = shutil.which("medc-inspect")
    assert exe, "medc-inspect is not on PATH: run `bash scripts/setup.sh` and `source scripts/env.sh`"
    ok = subprocess.run([exe, "--json", str(bundle_path)], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and json.loads(ok.stdout)["application"] == "target_localization"
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(torch.zeros(3).numpy().tobytes())
    failed = subprocess.run([exe, str(bad)], capture_output=True, text=True, timeout=120)
    assert failed.returncode == 1 and "invalid bundle" in failed.stderr and "Traceback" not in failed.stderr
