"""The output folder of medc-train and medc-clone against unusable targets: a file, a device
(/dev/full), a file in the way of a folder to make, and a name longer than the file system takes are
refused before any work in one line (status 2), nothing written, the file in the way untouched."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

TARGETS = {
    "file": "is not a folder: give a folder to write into",
    "/dev/full": "/dev/full is not a folder",
    "file on the way": "is not a folder: give a folder to write into (for ",
    "long name": "bytes the file system takes",
}


def _target(tmp_path: Path, kind: str) -> Path:
    victim = tmp_path / "victim.txt"
    return {"file": victim, "/dev/full": Path("/dev/full"), "file on the way": victim / "run",
            "long name": tmp_path / ("r" * 300)}[kind]


@pytest.mark.parametrize("command", ["medc-train", "medc-clone"])
@pytest.mark.parametrize("kind", list(TARGETS))
def test_an_unusable_output_folder_is_refused_before_the_work(command, kind, tmp_path, capsys):
    from medc_training.cli.clone import main as clone_main
    from medc_training.cli.train import main as train_main

    (tmp_path / "victim.txt").write_text("precious\n")
    out = _target(tmp_path, kind)
    args = ["--out", str(out), "--grid", "10", "--max-steps", "10"]
    code = (train_main if command == "medc-train" else clone_main)(args)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"{command}: error: ") and TARGETS[kind] in lines[0], lines[0]
    assert sorted(os.listdir(tmp_path)) == ["victim.txt"]
    assert (tmp_path / "victim.txt").read_text() == "precious\n"
    assert Path("/dev/full").is_char_device()


def test_a_sweep_is_refused_before_any_worker_starts(tmp_path, capsys):
    from medc_training.cli.train import main as train_main

    (tmp_path / "victim.txt").write_text("precious\n")
    code = train_main(["--out", str(tmp_path / "victim.txt"), "--seeds", "0", "1", "--jobs", "2"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "is not a folder" in err, err
    assert sorted(os.listdir(tmp_path)) == ["victim.txt"]


def test_a_folder_made_by_a_parallel_run_during_the_check_is_accepted(tmp_path, monkeypatch):
    """Two runs of one plan check their folders at once: the walk sees ``runs/`` missing, the other
    run makes it before the walk's next look. The folder it finds then is accepted, a file is not."""
    from medc_training import outfiles

    made = tmp_path / "runs"
    made.mkdir()
    monkeypatch.setattr(outfiles, "_nearest_folder", lambda target: tmp_path)  # the walk's stale view
    target = made / "medc" / "seed1"
    assert outfiles.check_output_folder(target) == target
    made.rmdir()
    made.write_text("not a folder\n")
    with pytest.raises(outfiles.OutputError, match="is not a folder"):
        outfiles.check_output_folder(target)
