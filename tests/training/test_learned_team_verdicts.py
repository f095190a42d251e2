"""The verdicts of docs/learned-team.md that decide its goal are rebuilt from the committed episode
lines by one command, byte for byte the committed verdict files."""

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_goals_verdicts_rebuild_from_the_committed_episode_lines():
    done = subprocess.run(["bash", str(ROOT / "scripts/learned_team_verdicts.sh")], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    same = [line for line in done.stdout.splitlines() if line.startswith("same  ")]
    assert len(same) == 6, done.stdout
    assert "DIFFERS" not in done.stderr
