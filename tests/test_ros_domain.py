"""Test processes running at once on one machine each hold a ROS domain of their own."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

CLAIM = ("import sys; sys.path.insert(0, {tests!r}); import ros_domain; print(ros_domain.claim_domain(), "
         "flush=True); sys.stdin.read()")


def test_processes_at_once_hold_different_domains_and_free_them_on_exit():
    code = CLAIM.format(tests=str(Path(__file__).parent))
    procs = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True) for _ in range(6)]
    try:
        domains = [int(p.stdout.readline()) for p in procs]  # all six hold theirs at this moment
    finally:
        for p in procs:
            p.communicate("")
    assert len(set(domains)) == 6 and all(100 <= d <= 199 for d in domains)
    again = subprocess.run([sys.executable, "-c", code], input="", capture_output=True, text=True, check=True)
    assert 100 <= int(again.stdout) <= 199  # the locks went with their holders
