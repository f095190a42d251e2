"""A run folder takes one training run at a time (medc_training.runs.lock_run_folder): a second
process locking the same folder is refused with the holder's pid, the folder's files untouched;
once the holder is killed (SIGKILL: no clean-up runs) the kernel has released the lock and the
next run takes it. A lock file planted as a link is refused, its target untouched."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from medc_training.runs import LOCK_FILE, RunFolderBusy, RunMismatch, lock_run_folder

HOLDER = textwrap.dedent("""
    import sys
    from medc_training.runs import lock_run_folder
    with lock_run_folder(sys.argv[1]):
        print("locked", flush=True)
        sys.stdin.read()  # hold it until the test closes stdin or kills this process
""")


def _holder(out) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()  # blocks until the lock is held (or the process died)
    assert line.strip() == "locked", proc.communicate(timeout=60)
    return proc


@pytest.mark.timing
def test_a_second_run_into_a_locked_folder_is_refused_until_the_first_dies(tmp_path):
    out = tmp_path / "run"
    first = _holder(out)
    try:
        (out / "metrics.csv").write_text("step,episode_length\n0,30\n")
        busy = rf"in use by another training run \(pid {first.pid}\)"
        with pytest.raises(RunFolderBusy, match=busy), lock_run_folder(out):
            (out / "metrics.csv").write_text("mixed\n")  # never reached
        assert (out / "metrics.csv").read_text() == "step,episode_length\n0,30\n"
    finally:
        first.send_signal(signal.SIGKILL)
        first.communicate(timeout=60)
    with lock_run_folder(out) as folder:  # the kernel released the dead holder's lock
        assert folder == out
        assert (out / LOCK_FILE).read_text().split()[0] == str(os.getpid())


def test_the_lock_is_released_at_the_end_of_a_run_and_refuses_a_link(tmp_path):
    out = tmp_path / "a" / "b"
    with lock_run_folder(out):
        pass
    with lock_run_folder(out):  # taken again once released
        pass
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / LOCK_FILE).symlink_to(victim)
    with pytest.raises(RunMismatch, match="is a symlink"), lock_run_folder(linked):
        pass
    assert victim.read_text() == "precious\n"
