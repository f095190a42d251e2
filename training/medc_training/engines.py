"""Engines that run a list of jobs: a local process pool (the default on one machine) or Ray
(a local Ray cluster, or one joined by address, for sweeps that outgrow one machine).

Both skip finished runs (:func:`.jobs.job_done`), show runs done / total, and leave nothing
half-written when interrupted (:func:`.jobs.run_job` publishes a run folder only when it is
finished), so rerunning the same command resumes.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

from .jobs import job_done, run_job

#: What an interrupted sweep leaves behind (said by the CLIs on Ctrl-C).
INTERRUPTED = ("finished runs are kept; unfinished ones left no run folder and resume from their "
               "checkpoint when the same command is run again")


def _worker_init(threads: int = 1, parent: int | None = None) -> None:
    """Set up a worker process: ``threads`` torch threads, and (``parent``: the sweep's pid) die
    with the sweep (:func:`die_with_parent`)."""
    import torch

    if parent is not None:
        die_with_parent(parent)
    torch.set_num_threads(threads)


#: prctl option: the signal a process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: Seconds between two looks at the parent where prctl is not there (not Linux).
WATCH_PARENT_EVERY_S = 1.0


def die_with_parent(parent: int) -> None:
    """End this process when ``parent`` (the pid that started it) ends, however it ends (SIGKILL
    included): the kernel's parent-death signal (``prctl(PR_SET_PDEATHSIG, SIGKILL)``) on Linux, a
    thread watching the parent pid elsewhere. A parent already gone before this ran ends it at once.
    A pool worker's run keeps its checkpoint in its partial folder, so a rerun resumes it."""
    import signal

    armed = False
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    if armed:
        return
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCH_PARENT_EVERY_S)
        os._exit(1)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


def _line(job: dict, summary: dict, start: float) -> str:
    return (f"{job['name']}: final episode length {summary['final_episode_length']:.1f} "
            f"({summary['train_seconds']:.0f}s, {time.time() - start:.0f}s elapsed)")


@dataclass
class LocalPool:
    """``workers`` processes on this machine (1: in this process), one torch thread each; they die
    with the process that started them, even when it is killed (:func:`die_with_parent`)."""

    workers: int = 1

    def describe(self) -> str:
        return f"{self.workers} worker(s)"

    def run(self, todo: list[dict], done) -> None:
        if self.workers <= 1:
            _worker_init()
            for job in todo:
                done(job, run_job(job))
            return
        # Workers die with this process even when it is SIGKILLed (no clean-up of its own runs then).
        pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_worker_init,
                                   initargs=(1, os.getpid()))
        try:
            futures = {pool.submit(run_job, job): job for job in todo}
            for fut in as_completed(futures):
                done(futures[fut], fut.result())
        except BaseException:  # Ctrl-C or a failed job: stop the workers, drop what has not started
            # (ProcessPoolExecutor has no public way to stop running work before Python 3.14)
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                proc.terminate()
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        pool.shutdown()


def _ray_task(job: dict, cwd: str, threads: int) -> dict:
    """A job on a Ray worker: in the driver's working directory (relative paths in the job, such
    as expert bundles and run folders, mean the same on every node of a shared file system)."""
    if os.path.isdir(cwd):
        os.chdir(cwd)
    _worker_init(threads)
    return run_job(job)


@dataclass
class RayCluster:
    """Each job is a Ray task asking for ``cpus_per_run`` CPUs and, when its config's device is
    cuda, ``gpus_per_run`` GPUs. ``address`` None starts a local cluster of ``num_cpus`` CPUs (None:
    all); otherwise joins the cluster there (e.g. ``HEAD:6379``, or ``auto``). Tasks whose worker
    or node dies are retried ``retries`` times (resuming from their checkpoint); past that they are
    left unfinished for the next rerun. When Ray is already initialised (a caller's ``ray.init``),
    that cluster is used and left running."""

    address: str | None = None
    num_cpus: int | None = None
    cpus_per_run: int = 1
    gpus_per_run: float = 1.0
    retries: int = 2

    def describe(self) -> str:
        return "Ray tasks on " + (f"the cluster at {self.address}" if self.address else "a local Ray cluster")

    def resources(self, job: dict) -> dict:
        cuda = str(job["config"].get("device", "cpu")).startswith("cuda")
        return {"num_cpus": self.cpus_per_run, "num_gpus": self.gpus_per_run if cuda else 0}

    def _check_feasible(self, ray, todo: list[dict]) -> None:
        """Refuse runs the cluster could never schedule (Ray would wait for them forever)."""
        have = ray.cluster_resources()
        for kind, key in (("CPU", "num_cpus"), ("GPU", "num_gpus")):
            need = max(self.resources(job)[key] for job in todo)
            if need > have.get(kind, 0):
                raise RuntimeError(
                    f"a run asks for {need:g} {kind}(s) but the Ray cluster has {have.get(kind, 0):g}: "
                    + ("start its workers with `ray start ... --num-gpus N`, or train on --device cpu"
                       if kind == "GPU" else "lower --cpus-per-run"))

    def run(self, todo: list[dict], done) -> None:
        try:
            import ray
        except ImportError as exc:
            raise RuntimeError("--ray needs the ray package: run scripts/setup.sh (it installs the pinned "
                               "ray from requirements.txt)") from exc
        started = not ray.is_initialized()
        if started:
            if self.address is None:
                ray.init(num_cpus=self.num_cpus, include_dashboard=False)
            else:
                ray.init(address=self.address)
        try:
            self._check_feasible(ray, todo)
        except BaseException:
            if started:
                ray.shutdown()
            raise
        task = ray.remote(_ray_task)
        cwd = os.getcwd()
        refs = {task.options(**self.resources(job), max_retries=self.retries, name=job["name"])
                .remote(job, cwd, self.cpus_per_run): job for job in todo}
        pending, lost = list(refs), []
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    try:
                        summary = ray.get(ref)
                    except ray.exceptions.RayTaskError as exc:  # the job itself failed: stop the sweep
                        raise exc.as_instanceof_cause() from None
                    except ray.exceptions.RayError as exc:  # its worker or node was lost, retries spent
                        lost.append(f"{refs[ref]['name']} ({type(exc).__name__})")
                        continue
                    done(refs[ref], summary)
        except BaseException:  # Ctrl-C or a failed job: cancel the rest (their runs stay unfinished)
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        finally:
            if started:
                ray.shutdown()
        if lost:
            raise RuntimeError(f"{len(lost)} run(s) lost their Ray worker and were left unfinished: "
                               f"{', '.join(lost)}; run the same command again to resume them")


def run_jobs(jobs: list[dict], engine, label: str) -> list[dict]:
    """Run the unfinished ``jobs`` on ``engine``, with a runs done / total progress bar and one
    line per finished run; returns the summaries of the runs this call finished."""
    todo = [j for j in jobs if not job_done(j)]
    print(f"[{label}] {len(jobs) - len(todo)} of {len(jobs)} runs already done; running {len(todo)} "
          f"on {engine.describe()}", flush=True)
    finished: list[dict] = []
    if not todo:
        return finished
    start = time.time()
    from .console import progress_bar

    with progress_bar(len(jobs), initial=len(jobs) - len(todo), unit="run", desc=label) as bar:
        def done(job: dict, summary: dict) -> None:
            finished.append(summary)
            bar.write(f"  {_line(job, summary, start)}")
            bar.update(1)

        engine.run(todo, done)
    return finished


def add_engine_arguments(p: argparse.ArgumentParser) -> None:
    """--jobs / --ray / --cpus-per-run / --gpus-per-run: where the runs of a sweep go."""
    p.add_argument("--jobs", type=int,
                   help="runs at once on this machine: worker processes (default 2, or the CPU count if "
                        "lower); with a local --ray, the CPUs of the local cluster (default all)")
    p.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="run each run as a Ray task: alone, on a local Ray cluster; with ADDRESS (HEAD:6379, "
                        "or auto), on that existing cluster")
    p.add_argument("--cpus-per-run", type=int, default=1, help="with --ray: CPUs (torch threads) per run")
    p.add_argument("--gpus-per-run", type=float, default=1.0,
                   help="with --ray: GPUs per run whose device is cuda (fractions share a GPU; default 1)")


def engine_from_args(args: argparse.Namespace):
    """The engine the parsed --jobs / --ray arguments name."""
    if args.ray is None:
        return LocalPool(args.jobs or min(2, os.cpu_count() or 1))
    if args.cpus_per_run < 1 or args.gpus_per_run < 0:
        raise ValueError("--cpus-per-run must be >= 1 and --gpus-per-run >= 0")
    return RayCluster(address=None if args.ray == "local" else args.ray,
                      num_cpus=args.jobs if args.ray == "local" else None,
                      cpus_per_run=args.cpus_per_run, gpus_per_run=args.gpus_per_run)
