"""A sweep's pool workers die with it, even when it is SIGKILLed (no clean-up of its own runs), and
their checkpoints are kept for the rerun; two training runs into one ``--out`` at once: the second is
refused naming the first's pid, and the first's run is not touched."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from medc_training.bundle import load_state
from medc_training.jobs import partial_dir
from medc_training.runner import CHECKPOINT

TINY_ARGS = ["--agents", "2", "--walls", "0", "--grid", "6", "--max-steps", "12", "--num-envs", "4",
             "--horizon", "32", "--epochs", "1", "--eval-every", "128", "--eval-steps", "16",
             "--eval-envs", "4", "--eval-episodes", "4", "--quiet", "--no-tensorboard"]
#: Seconds a loaded machine is given for what these tests wait on (the deadline, not a sleep).
DEADLINE_S = 180.0


def _train(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "medc_training.cli.train", *TINY_ARGS, *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _wait_for_checkpoint(proc: subprocess.Popen, ckpt: Path, updates: int = 1) -> dict:
    """The checkpoint's state once it holds ``updates`` updates (``proc`` must keep running)."""
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        try:
            if ckpt.exists():
                state = load_state(ckpt)
                if state["learner"]["updates"] >= updates:
                    return state
        except ValueError:  # read while being replaced
            pass
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(0.2)
    raise AssertionError(f"no checkpoint with {updates} updates at {ckpt} within {DEADLINE_S:g}s")


def _children(pid: int) -> list[int]:
    """The pids whose parent is ``pid``."""
    out = []
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry))
    return out


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its new parent to reap it does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.timing
def test_a_sigkilled_sweep_leaves_no_worker_running(tmp_path):
    out = tmp_path / "sweep"
    proc = _train("--steps", "100000", "--seeds", "0", "1", "--jobs", "2", "--out", str(out))
    ckpts = [partial_dir(out / f"seed-{s}") / CHECKPOINT for s in (0, 1)]
    workers: list[int] = []
    try:
        for ckpt in ckpts:
            _wait_for_checkpoint(proc, ckpt)
        workers = _children(proc.pid)
        assert len(workers) >= 2, workers
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=60) == -signal.SIGKILL
        deadline = time.monotonic() + DEADLINE_S
        while any(map(_alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)], "a pool worker outlived its sweep"
    finally:
        for pid in [proc.pid, *workers]:  # only the processes this test started
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.wait()
    for ckpt in ckpts:  # what the workers had done is kept for the rerun
        assert load_state(ckpt)["learner"]["updates"] >= 1


@pytest.mark.timing
def test_two_runs_into_one_out_at_once_the_second_is_refused(tmp_path, capsys):
    from medc_training.cli.train import main

    out = tmp_path / "run"
    first = _train("--steps", "100000", "--seed", "3", "--out", str(out))
    try:
        _wait_for_checkpoint(first, out / CHECKPOINT)
        # --overwrite (or --resume) would take a folder a finished or killed run left; never a live one's.
        for flag in ("--overwrite", "--resume"):
            assert main([*TINY_ARGS, "--steps", "256", "--seed", "4", "--out", str(out), flag]) == 2
            err = capsys.readouterr().err
            assert err.strip() == (f"medc-train: error: {out} is in use by another training run (pid "
                                   f"{first.pid}): two runs into one folder would mix their metrics and "
                                   "checkpoints; wait for it to end, or use another --out")
        state = _wait_for_checkpoint(first, out / CHECKPOINT, updates=2)  # the first runs on
        assert state["config"]["seed"] == 3
        assert not (out / "summary.json").exists() and not (out / "policy.safetensors").exists()
    finally:
        first.kill()
        first.wait()
    import csv

    with open(out / "metrics.csv", newline="") as fh:
        steps = [int(float(row["step"])) for row in csv.DictReader(fh)]
    assert steps and steps == sorted(set(steps))  # one run's rows: none of the refused run's step 0 again
