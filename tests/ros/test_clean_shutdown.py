"""Stopping the multi-process graph (the launcher's SIGINT to every node) leaves no FATAL log or
traceback: a SIGINT only ends a node's spin loop; the executor, the node and the context are shut
down after it, so no callback publishes on a dead context. The registry bridge removes the
temporary folders it made (its bundle cache, its content store) when it exits."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

#: Launch/stop cycles per run (MEDC_SHUTDOWN_CYCLES sets more; scripts/flake_check.sh repeats the
#: whole test, 10 runs of 5 cycles by default).
CYCLES = int(os.environ.get("MEDC_SHUTDOWN_CYCLES", "5"))
#: What no process of the graph may print, on stdout or stderr.
BAD = ("FATAL", "Traceback", "ERROR")
#: What the registry bridge logs once it serves.
BRIDGE_UP = "registry bridge on /medc/registry/fetch_bundle"


@pytest.mark.timing
@pytest.mark.ros
@pytest.mark.slow
def test_repeated_launch_and_stop_logs_no_fatal_or_traceback(bundles, tmp_path):
    """CYCLES times: the simulator, an agent and the registry bridge (no cache_dir, no content:
    both temporary folders of its own) as processes, playing episodes on a 10x10 grid; once the
    bridge serves and an episode was played, Ctrl-C to the launcher, which stops every node with a
    SIGINT. Every node's stdout and stderr go to the launcher's (children inherit them), so both
    are checked; the bridge's temporary folders land in this test's TMPDIR and must be gone. One
    agent and short episodes keep a cycle cheap (each node process costs 2 to 3 s of CPU to
    start, mostly imports): a cycle takes about 7 s on the 2 shared cores here."""
    from ros_helpers import stop_launcher

    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 1\nmax_steps: 10\nagents: 1\npolicy: {bundles['a']}\n"
                      "registry: {enabled: true, params: {}}\n")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = os.environ | {"TMPDIR": str(scratch)}
    start = time.monotonic()
    for cycle in range(CYCLES):
        err, std = tmp_path / f"stderr-{cycle}.txt", tmp_path / f"stdout-{cycle}.txt"
        args = [sys.executable, "-m", "medc_bringup.launcher", "--config", str(config), "--seed", str(cycle)]
        # Files, not pipes: the nodes' logs can never block.
        with std.open("w") as out_file, err.open("w") as err_file:
            proc = subprocess.Popen(args, stdout=out_file, stderr=err_file, text=True, cwd=tmp_path, env=env,
                                    start_new_session=True)
        try:
            # Every node is up and at work (the bridge starts on its own, unwaited for by the
            # simulator's start gate), then Ctrl-C.
            deadline = time.monotonic() + 120
            while not (BRIDGE_UP in err.read_text() and "episode 0:" in std.read_text()):
                assert proc.poll() is None, f"cycle {cycle}: the launcher ended:\n{err.read_text()[-3000:]}"
                assert time.monotonic() < deadline, f"cycle {cycle}: no bridge or no episode:\n" \
                                                    f"{err.read_text()[-3000:]}"
                time.sleep(0.1)
            proc.send_signal(signal.SIGINT)
            try:
                code = proc.wait(60)
            except subprocess.TimeoutExpired:
                pytest.fail(f"cycle {cycle}: the launcher did not stop within 60 s of Ctrl-C:\n"
                            f"{err.read_text()[-3000:]}")
        finally:
            if proc.poll() is None:
                stop_launcher(proc)
        text, out = err.read_text(), std.read_text()
        assert code == 0, f"cycle {cycle}:\n{text[-3000:]}"
        *played, last = out.strip().splitlines()
        assert played and all(re.fullmatch(r"episode \d+: \d+ steps, (target found|truncated)", line)
                              for line in played), f"cycle {cycle} stdout:\n{out[-3000:]}"
        assert json.loads(last)["episodes"] == len(played), f"cycle {cycle} stdout:\n{out[-3000:]}"
        for name, stream in (("stderr", text), ("stdout", out)):
            bad = [line for line in stream.splitlines() if any(word in line for word in BAD)]
            assert not bad, f"cycle {cycle} {name}:\n" + "\n".join(bad[:20]) + f"\n...\n{stream[-3000:]}"
        left = sorted(p.name for p in scratch.iterdir())
        assert left == [], f"cycle {cycle} left temporary files: {left}"
    elapsed = time.monotonic() - start
    print(f"{CYCLES} clean launch/stop cycles in {elapsed:.0f} s ({elapsed / CYCLES:.1f} s each)")
