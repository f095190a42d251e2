"""A run folder holds one configuration: what it records, and how a resume or
an "already done" check compares it.

A run is its :class:`~medc_training.config.TrainConfig` plus its *inputs*, what else its learner
was built from: the expert specs (paths or names) and their weights, and the FRL users whose own
curves it logs. ``summary.json`` (a finished run) and ``checkpoint.safetensors`` (a running one)
record both (``config``, ``inputs``). Every field is compared, except:

* ``torch_threads`` everywhere (how many CPU threads computed it, not what was computed);
* ``total_steps`` when resuming (a killed run may be carried on to another step count: the steps
  before are the same whatever the total).

A record written before inputs were recorded (the committed docs/reproduction runs) compares its
config only; a config recorded before a field existed reads as :meth:`TrainConfig.from_dict` says.

A folder takes one run at a time: :func:`lock_run_folder` holds an exclusive lock on
``<folder>/.run.lock`` (``flock``: the kernel releases it when the holder exits or is killed), so a
second run into the same folder is refused with the holder's pid instead of mixing its metrics
into the first's.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from medc_training.outfiles import check_output_folder

#: Fields never compared: they do not change what a run computes.
PERFORMANCE_ONLY = ("torch_threads",)
#: Fields a resumed run may change.
RESUME_FREE = ("total_steps", *PERFORMANCE_ONLY)


class RunMismatch(ValueError):
    """A run folder holds another configuration than the one asked for; the message names every
    differing field and what to do."""


class RunFolderBusy(RunMismatch):
    """Another run holds the run folder's lock; the message names its pid and what to do."""


#: The lock file :func:`lock_run_folder` holds in a run folder.
LOCK_FILE = ".run.lock"


@contextlib.contextmanager
def lock_run_folder(out: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold ``out``'s run lock (the folder is created if missing) for the ``with`` block; yields the
    folder. The lock file is opened without following a link and records the holder's pid and start
    time, for the refusal of a second run.

    Raises:
        RunFolderBusy: another process holds it (the message names its pid).
        RunMismatch: the lock file is a link or not a regular file.
        OutputError: ``out`` cannot be a folder to write into (``outfiles.check_output_folder``).
    """
    folder = Path(out)
    check_output_folder(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_FILE
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise RunMismatch(f"{lock} is a symlink: a run folder's lock must be a plain file; remove "
                              "the link") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise RunMismatch(f"{lock} is not a regular file: a run folder's lock must be one")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("ascii", "replace").split()
            who = f"pid {holder[0]}" if holder and holder[0].isdigit() else "another process"
            raise RunFolderBusy(f"{folder} is in use by another training run ({who}): two runs into "
                                "one folder would mix their metrics and checkpoints; wait for it to "
                                "end, or use another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {time.time():.0f}\n".encode(), 0)
        yield folder
    finally:
        os.close(fd)  # releases the lock


def run_inputs(experts=(), expert_weights=None, side_users=()) -> dict[str, Any]:
    """The inputs record of a run: expert specs, their weights (None: by the QoS rule), FRL side users."""
    return {"experts": [str(e) for e in experts or ()],
            "expert_weights": None if expert_weights is None else [float(w) for w in expert_weights],
            "side_users": [int(u) for u in side_users or ()]}


def job_inputs(job: dict) -> dict[str, Any]:
    """:func:`run_inputs` of an experiment job dict (medc_lab.plan)."""
    return run_inputs(job.get("experts", ()), job.get("expert_weights"), job.get("side_users", ()))


def _plain(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def differences(recorded_config: dict, recorded_inputs: dict | None, config: dict, inputs: dict | None,
                ignore: tuple[str, ...] = PERFORMANCE_ONLY) -> list[str]:
    """``field=recorded vs wanted`` for every field that differs (sorted; empty when none).

    ``recorded_inputs`` None (recorded before inputs were) compares the config only.
    """
    from .config import TrainConfig

    try:
        old = _plain(TrainConfig.from_dict(recorded_config).to_dict())
    except (TypeError, ValueError) as exc:
        return [f"the recorded config cannot be read ({exc})"]
    new = _plain(TrainConfig.from_dict(config).to_dict())
    out = [f"{key}={old.get(key)!r} recorded vs {new.get(key)!r} now"
           for key in sorted(set(old) | set(new)) if key not in ignore and old.get(key) != new.get(key)]
    if recorded_inputs is not None and inputs is not None:
        a, b = _plain(recorded_inputs), _plain(inputs)
        out += [f"{key}={a.get(key)!r} recorded vs {b.get(key)!r} now"
                for key in sorted(set(a) | set(b)) if a.get(key) != b.get(key)]
    return out


def check_finished(summary: dict, config: dict, inputs: dict | None, where: str,
                   flag: str = "--overwrite") -> bool:
    """True when the finished run ``summary`` (its summary.json) is the run ``config`` + ``inputs``
    describe.

    Raises:
        RunMismatch: it is another run; the message names the differing fields and ``flag``.
    """
    diffs = differences(summary.get("config", {}), summary.get("inputs"), config, inputs)
    if diffs:
        raise RunMismatch(f"{where} holds a finished run of another configuration ({'; '.join(diffs)}); "
                          f"give {flag} to replace it, or use another output folder")
    return True
