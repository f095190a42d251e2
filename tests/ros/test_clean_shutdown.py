"""Stopping the multi-process graph (the launcher's SIGINT to every node) leaves no FATAL log or
traceback: a SIGINT only ends a node's spin loop; the executor, the node and the context are shut
down after it, so no callback publishes on a dead context."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

#: Launch/stop cycles run at least, and the wall time after which no new cycle starts.
MIN_RUNS = 3
BUDGET_S = float(os.environ.get("MEDC_SHUTDOWN_BUDGET_S", "110"))


@pytest.mark.ros
@pytest.mark.slow
def test_repeated_launch_and_stop_logs_no_fatal_or_traceback(bundles, tmp_path):
    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 1\nmax_steps: 20\nseed: 5\npolicy: {bundles['a']}\n")
    launcher = Path(sys.executable).parent / "medc-launch"
    start = time.monotonic()
    runs = 0
    while runs < MIN_RUNS or time.monotonic() - start < BUDGET_S:
        err = tmp_path / f"stderr-{runs}.txt"
        with err.open("w") as log:  # a file, not a pipe: the nodes' logs can never block
            out = subprocess.run([str(launcher), "--config", str(config), "--episodes", "3", "--seed",
                                  str(runs), "--quiet"], stdout=subprocess.PIPE, stderr=log, text=True,
                                 timeout=120)
        text = err.read_text()
        assert out.returncode == 0, text[-2000:]
        assert '"episodes": 3' in out.stdout
        assert "FATAL" not in text and "Traceback" not in text, f"run {runs}:\n{text[-3000:]}"
        runs += 1
    print(f"{runs} clean launch/stop cycles in {time.monotonic() - start:.0f} s")
