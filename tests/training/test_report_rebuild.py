"""The committed reproduction report is exactly what the report builder makes from the committed runs."""

import os
import shlex
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
COMMITTED = REPO / "docs" / "reproduction"


def test_committed_report_is_rebuilt_byte_for_byte_from_the_committed_runs(tmp_path, monkeypatch):
    from medc_lab.cli.reproduce import main

    report = (COMMITTED / "report.md").read_text()
    marker = "# report rebuilt with: medc-reproduce "
    rebuilt_with = [line for line in report.splitlines() if line.startswith(marker)]
    if not rebuilt_with:
        pytest.fail("docs/reproduction/report.md does not say how it was rebuilt; rebuild it with "
                    "medc-reproduce --scale cpu --seeds 3 --only report --out docs/reproduction")
    argv = shlex.split(rebuilt_with[-1][len(marker):])
    out = Path(argv[argv.index("--out") + 1])
    assert not out.is_absolute() and "--models" not in argv
    # the inputs the builder reads, at the same relative paths (so "Made by" names the same command)
    dest = tmp_path / out
    shutil.copytree(COMMITTED / "runs", dest / "runs")
    for name in ("command.txt", "random_play.json", "protocol.md", "discussion.md"):
        if (COMMITTED / name).exists():
            shutil.copy(COMMITTED / name, dest / name)
    os.symlink(REPO / "models", tmp_path / "models")
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    rebuilt = (dest / "report.md").read_text()
    assert rebuilt == report, ("the report builder no longer makes docs/reproduction/report.md from the "
                               "committed runs: rebuild it (medc-reproduce ... --only report) and commit it")
    # rebuilding measured nothing new: random play was already cached for every gate
    assert (dest / "random_play.json").read_text() == (COMMITTED / "random_play.json").read_text()
