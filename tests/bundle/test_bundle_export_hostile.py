"""medc-inspect --export against hostile input: a bundle the agents refuse (its dry run) is refused
with the agents' reason and nothing is written; the export never writes onto its input bundle (by
name, through a link, or as OUT.json), never through a planted link, and over an existing file only
with --overwrite; a folder or a device as OUT is refused before anything is exported."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from medc_training.bundle import BundleError, load_untrusted
from medc_training.bundle import policy as policy_mod
from medc_training.cli.inspect import main as inspect_main

TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"


@pytest.fixture()
def source(tmp_path) -> Path:
    """A copy of the shipped team's bundle in its own folder."""
    d = tmp_path / "in"
    d.mkdir()
    return Path(shutil.copy(TEAM, d / "team.safetensors"))


def _export(capsys, *args: str) -> tuple[int, str]:
    code = inspect_main(["--export", "torchscript", *map(str, args)])
    return code, capsys.readouterr().err


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("medc-inspect: ") and "Traceback" not in err, err
    return lines[0]


def test_a_bundle_the_agents_refuse_is_refused_with_their_reason(source, tmp_path, capsys, monkeypatch):
    # Every agent on this machine would refuse it: no observation passes the dry run in 1 ns.
    monkeypatch.setattr(policy_mod, "MAX_FORWARD_SECONDS", 1e-9)
    policy_mod.forget_refusals()
    out = tmp_path / "out" / "team.pt"
    out.parent.mkdir()
    code, err = _export(capsys, source, out)
    assert code == 1
    line = _one_line(err)
    assert "over the 1e-09 s limit (too slow to act with" in line
    policy_mod.forget_refusals()
    with pytest.raises(BundleError) as agents:  # what every agent calls with a bundle from the graph
        load_untrusted(str(source), max_forward_s=policy_mod.MAX_FORWARD_SECONDS)
    reason = line.removeprefix("medc-inspect: ")
    assert reason.split(" takes ")[0] == str(agents.value).split(" takes ")[0]
    assert "too slow to act with" in str(agents.value)
    assert list(out.parent.iterdir()) == []  # nothing written, no temporary file left


@pytest.mark.parametrize("how", ["same name", "link to the bundle", "OUT.json is the bundle"])
def test_the_export_never_writes_onto_its_input(source, tmp_path, capsys, how):
    before = source.read_bytes()
    if how == "same name":
        out = source
    elif how == "link to the bundle":
        out = tmp_path / "team.pt"
        out.symlink_to(source)
    else:
        out = source.with_name("team.pt")
        source = Path(shutil.move(source, source.with_name("team.pt.json")))
    code, err = _export(capsys, source, out, "--overwrite")
    assert code == 1
    assert "is the bundle being exported (or a link to it)" in _one_line(err)
    assert source.read_bytes() == before
    assert not [p for p in source.parent.iterdir() if p.name.endswith(".tmp")]


def test_an_existing_file_or_link_is_replaced_only_when_asked(source, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "team.pt"
    out.symlink_to(victim)
    code, err = _export(capsys, source, out)
    assert code == 1 and "exists (a link): not overwritten; give --overwrite" in _one_line(err)
    assert out.is_symlink() and victim.read_text() == "precious\n"
    assert _export(capsys, source, out, "--overwrite")[0] == 0  # the link is replaced, not followed
    assert not out.is_symlink() and out.stat().st_size > 1000 and victim.read_text() == "precious\n"
    side = tmp_path / "team.pt.json"
    side.write_text("{}\n")  # now both exist: refused again without --overwrite, nothing touched
    model = out.read_bytes()
    out.write_bytes(b"mine\n")
    code, err = _export(capsys, source, out)
    assert code == 1 and "exists (a file): not overwritten" in _one_line(err)
    assert out.read_bytes() == b"mine\n" and side.read_text() == "{}\n"
    assert _export(capsys, source, out, "--overwrite")[0] == 0
    assert out.read_bytes()[:2] == b"PK" and len(out.read_bytes()) > len(model) // 2  # a TorchScript archive
    assert '"model_format": "torchscript"' in side.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "team.pt", "team.pt.json", "victim.txt"]


@pytest.mark.parametrize("target", ["folder", "/dev/full", "long name"])
def test_an_unusable_target_is_refused_before_the_export(source, tmp_path, capsys, target):
    out = {"folder": tmp_path, "/dev/full": Path("/dev/full"),
           "long name": tmp_path / ("m" * 300 + ".pt")}[target]
    code, err = _export(capsys, source, out, "--overwrite")
    assert code == 1
    line = _one_line(err)
    assert {"folder": "is a folder", "/dev/full": "is not a regular file (a device",
            "long name": "the name is longer than"}[target] in line
    if target == "/dev/full":
        assert Path("/dev/full").is_char_device() and not os.path.islink("/dev/full")
