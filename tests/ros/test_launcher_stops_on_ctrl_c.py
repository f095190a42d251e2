"""medc-launch runs the graph as separate processes and stops all of them on Ctrl-C."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest


@pytest.mark.timing
@pytest.mark.ros
def test_ctrl_c_stops_the_graph_and_prints_the_summary(bundles, tmp_path):
    config = tmp_path / "launch.yaml"
    cache = tmp_path / "bridge-cache"
    config.write_text(
        f"grid: 10\nwalls: 1\nmax_steps: 20\nseed: 5\npolicy: {bundles['a']}\n"
        f"registry: {{enabled: true, params: {{cache_dir: {cache}}}}}\n"
    )
    launcher = Path(sys.executable).parent / "medc-launch"
    log = (tmp_path / "stderr.txt").open("w")  # a file, not a pipe: the nodes' logs can never block
    # --timeout: a graph that never plays ends the launcher (and the wait for its first line) by itself.
    proc = subprocess.Popen([str(launcher), "--config", str(config), "--timeout", "300"],
                            stdout=subprocess.PIPE, stderr=log, text=True)
    try:
        first = proc.stdout.readline()  # blocks until the first episode ends
        assert first.startswith("episode 0:"), first
        proc.send_signal(signal.SIGINT)
        start = time.monotonic()
        rest, _ = proc.communicate(timeout=60)
        # The launcher gives its nodes 5 s to stop on its SIGINT, then kills them: well within this.
        assert time.monotonic() - start < 15
    finally:
        if proc.poll() is None:
            proc.kill()
    log.close()
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()[-2000:]
    summary = json.loads(rest.strip().splitlines()[-1])
    assert summary["episodes"] >= 1 and summary["episode_lengths"][0] == int(first.split()[2])
    # No node of this graph survives its launcher: agents (named by their policy), bridge (its cache).
    for pattern in (str(bundles["a"]), str(cache)):
        leftovers = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout.split()
        assert leftovers == [], pattern


class _TakeFails:
    """An executor whose spin_once fails as rclpy's does when the context is shut down while a message
    is being taken (pybind11: "Unable to convert call argument '0' to Python object")."""

    def __init__(self, shut_down_first: bool) -> None:
        self.shut_down_first = shut_down_first

    def spin_once(self, timeout_sec: float) -> None:
        import rclpy

        if self.shut_down_first:
            rclpy.try_shutdown()
        raise RuntimeError("Unable to convert call argument '0' to Python object")


@pytest.mark.ros
def test_a_take_that_fails_because_ctrl_c_shut_rclpy_down_ends_the_spin_quietly(rclpy_context):
    from medc_common.executors import spin_once_alive

    # With rclpy still up, the same error is a real one and is raised.
    with pytest.raises(RuntimeError, match="call argument"):
        spin_once_alive(_TakeFails(shut_down_first=False), 0.01)
    assert spin_once_alive(_TakeFails(shut_down_first=True), 0.01) is False
