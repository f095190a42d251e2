"""Sweeps: the same jobs on a local Ray cluster and in the local process pool give the same runs;
finished runs are skipped; an interrupted run leaves no run folder and a rerun resumes it."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from child_signals import default_sigint
from medc_training.bundle import load_state
from medc_training.metrics import read_metrics
from medc_training.runner import CHECKPOINT

ray = pytest.importorskip("ray", reason="ray is installed by scripts/setup.sh (requirements.txt)")

from medc_training.config import TrainConfig  # noqa: E402
from medc_training.engines import LocalPool, RayCluster, run_jobs  # noqa: E402
from medc_training.jobs import SUMMARY, partial_dir, run_job  # noqa: E402

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_every=128, eval_steps=16, eval_envs=4, eval_episodes=4)
TINY_ARGS = ["--agents", "2", "--walls", "0", "--grid", "6", "--max-steps", "12", "--num-envs", "4",
             "--horizon", "32", "--epochs", "1", "--eval-every", "128", "--eval-steps", "16",
             "--eval-envs", "4", "--eval-episodes", "4", "--quiet", "--no-tensorboard"]


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray cluster of 2 CPUs for the module (the engines use it and leave it running)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def _plan(out: Path, steps: int = 1024) -> list[dict]:
    """Two runs of a tiny sparse/MEDC plan, seeds 0 and 1."""
    jobs = []
    for seed, (method, experts) in enumerate((("sparse", []), ("medc", ["random", "biased:2"]))):
        cfg = TrainConfig(method=method, total_steps=steps, seed=seed, **TINY).to_dict()
        jobs.append({"name": f"{method}/seed{seed}", "config": cfg, "experts": experts,
                     "out": str(out / "runs" / method / f"seed{seed}")})
    return jobs


def _results(job: dict) -> tuple:
    """What a run computed: its evaluation rows and summary, less the wall-clock fields."""
    out = Path(job["out"])
    rows = [{k: v for k, v in r.items() if k not in ("sps", "wall_time")}
            for r in read_metrics(out / "metrics.csv")]
    summary = json.loads((out / SUMMARY).read_text())
    return rows, {k: v for k, v in summary.items() if k != "train_seconds"}


@pytest.mark.timing
def test_a_plan_on_local_ray_equals_the_process_pool_runs_and_a_rerun_skips_them(local_ray, tmp_path, capsys):
    pool_jobs, ray_jobs = _plan(tmp_path / "pool"), _plan(tmp_path / "ray")
    assert len(run_jobs(pool_jobs, LocalPool(2), "pool")) == 2
    assert len(run_jobs(ray_jobs, RayCluster(), "ray")) == 2
    assert "2/2" in capsys.readouterr().err  # progress: runs done / total
    for a, b in zip(pool_jobs, ray_jobs):
        rows, summary = _results(a)
        assert len(rows) == 9 and summary["steps"] == 1024
        assert (rows, summary) == _results(b)
        assert not partial_dir(Path(b["out"])).exists() and not (Path(b["out"]) / CHECKPOINT).exists()
    # a finished run is never redone; a new one in the same plan is the only one run
    stamps = [(Path(j["out"]) / SUMMARY).stat().st_mtime_ns for j in ray_jobs]
    more = _plan(tmp_path / "ray")
    more[1] = {**more[1], "name": "medc/seed2", "config": {**more[1]["config"], "seed": 2},
               "out": str(tmp_path / "ray" / "runs" / "medc" / "seed2")}
    assert len(run_jobs([*ray_jobs, more[1]], RayCluster(), "ray")) == 1
    assert "2 of 3 runs already done" in capsys.readouterr().out
    assert [(Path(j["out"]) / SUMMARY).stat().st_mtime_ns for j in ray_jobs] == stamps


@pytest.mark.timing
def test_medc_train_seed_sweep_on_ray_equals_the_pool_sweep(local_ray, tmp_path, capsys):
    from medc_training.cli.train import main

    base = [*TINY_ARGS, "--method", "medc", "--expert", "random", "--steps", "512", "--seeds", "4", "5"]
    assert main([*base, "--out", str(tmp_path / "pool"), "--jobs", "1"]) == 0
    assert main([*base, "--out", str(tmp_path / "ray"), "--ray"]) == 0
    printed = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [sorted(p["runs"]) for p in printed] == [["seed-4", "seed-5"]] * 2
    for seed in (4, 5):
        pool = {"out": str(tmp_path / "pool" / f"seed-{seed}")}
        ray_run = {"out": str(tmp_path / "ray" / f"seed-{seed}")}
        assert _results(pool) == _results(ray_run) and _results(pool)[1]["config"]["seed"] == seed
        for d in (tmp_path / "pool", tmp_path / "ray"):  # each seed is a whole medc-train run
            assert {"policy.safetensors", "learning_curve.png", CHECKPOINT} <= {
                p.name for p in (d / f"seed-{seed}").iterdir()}
    # the sweep flags are refused without --seeds, and experts with a method that ignores them
    assert main([*TINY_ARGS, "--out", str(tmp_path / "x"), "--seeds", "1", "--method", "sparse",
                 "--expert", "random"]) == 2
    assert "only used by method medc or il" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*TINY_ARGS, "--out", str(tmp_path / "x"), "--ray"])
    assert not (tmp_path / "x").exists()


def _wait_for_checkpoint(proc, ckpt: Path, updates: int = 2, timeout: float = 120) -> None:
    """Wait until ``ckpt`` holds ``updates`` updates (``proc``, if given, must still be running)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if ckpt.exists() and load_state(ckpt)["learner"]["updates"] >= updates:
                return
        except ValueError:  # read while being replaced
            pass
        assert proc is None or proc.poll() is None, proc.stderr.read().decode()
        time.sleep(0.2)
    raise AssertionError(f"no checkpoint with {updates} updates at {ckpt} within {timeout}s")


@pytest.mark.timing
def test_a_killed_job_leaves_no_run_folder_and_the_rerun_resumes_it(tmp_path):
    job = _plan(tmp_path, steps=100_000)[0]
    code = ("import json; from medc_training.jobs import run_job; "
            f"run_job(json.loads({json.dumps(job)!r}))")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    out = Path(job["out"])
    try:
        _wait_for_checkpoint(proc, partial_dir(out) / CHECKPOINT)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not out.exists(), "a killed run must not leave a run folder"
    saved = load_state(partial_dir(out) / CHECKPOINT)["learner"]["global_step"]
    assert saved >= 64
    job["config"]["total_steps"] = saved + 64
    summary = run_job(job)
    assert summary["steps"] == saved + 64 and not partial_dir(out).exists()
    steps = [int(r["step"]) for r in read_metrics(out / "metrics.csv")]
    assert steps == sorted(set(steps)) and steps[0] == 0 and steps[-1] == saved + 64  # resumed, not restarted


@pytest.mark.timing
def test_ctrl_c_stops_a_pool_sweep_and_leaves_no_run_folders(tmp_path):
    out = tmp_path / "sweep"
    args = [sys.executable, "-m", "medc_training.cli.train", *TINY_ARGS, "--steps", "100000",
            "--seeds", "0", "1", "--jobs", "2", "--out", str(out)]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=default_sigint)
    ckpts = [partial_dir(out / f"seed-{s}") / CHECKPOINT for s in (0, 1)]
    try:
        for ckpt in ckpts:
            _wait_for_checkpoint(proc, ckpt, updates=1)
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=60) == 130
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "interrupted; finished runs are kept" in proc.stderr.read().decode()
    assert not any((out / f"seed-{s}").exists() for s in (0, 1))
    stamps = [c.stat().st_mtime_ns for c in ckpts]
    time.sleep(1.5)
    assert [c.stat().st_mtime_ns for c in ckpts] == stamps, "the pool's workers were stopped"


def _ray_worker_running(task_name: str) -> int | None:
    """The pid of the Ray worker whose process title says it runs ``task_name`` (ray::NAME)."""
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].decode().strip()
        except OSError:
            continue
        if title == f"ray::{task_name}":
            return int(pid)
    return None


def _kill_worker_mid_run(job: dict, engine: RayCluster) -> BaseException | None:
    """Run ``job`` on ``engine`` in a thread, SIGKILL its Ray worker after 2 updates; the engine's
    error (None when it finished the job)."""
    import threading

    result: dict = {}

    def sweep() -> None:
        try:
            run_jobs([job], engine, "lost")
        except BaseException as exc:
            result["error"] = exc

    thread = threading.Thread(target=sweep)
    thread.start()
    _wait_for_checkpoint(None, partial_dir(Path(job["out"])) / CHECKPOINT)
    pid = _ray_worker_running(job["name"])
    assert pid is not None, "the job's Ray worker was not found"
    os.kill(pid, signal.SIGKILL)
    thread.join(timeout=180)
    assert not thread.is_alive()
    return result.get("error")


@pytest.mark.timing
def test_a_lost_ray_worker_is_retried_or_left_unfinished_for_the_rerun(local_ray, tmp_path):
    job = _plan(tmp_path, steps=2048)[0]
    job["name"] = f"lost-{os.getpid()}/seed0"  # its worker's process title, unique on the machine
    out = Path(job["out"])
    # with a retry, the task starts again on a new worker and resumes from the checkpoint
    assert _kill_worker_mid_run(job, RayCluster(retries=1)) is None
    steps = [int(r["step"]) for r in read_metrics(out / "metrics.csv")]
    assert steps == sorted(set(steps)) and steps[-1] == 2048 and not partial_dir(out).exists()
    # without one, the run is left unfinished (no run folder) and the next rerun finishes it
    job = {**job, "name": f"lost-{os.getpid()}/seed1", "out": str(tmp_path / "lost1")}
    error = _kill_worker_mid_run(job, RayCluster(retries=0))
    assert isinstance(error, RuntimeError) and "run the same command again to resume" in str(error)
    assert not Path(job["out"]).exists() and (partial_dir(Path(job["out"])) / CHECKPOINT).exists()
    assert len(run_jobs([job], RayCluster(), "rerun")) == 1
    assert json.loads((Path(job["out"]) / SUMMARY).read_text())["steps"] == 2048


@pytest.mark.timing
def test_runs_the_ray_cluster_cannot_schedule_are_refused_not_waited_for(local_ray, tmp_path):
    job = _plan(tmp_path)[0]
    job["config"]["device"] = "cuda"
    if ray.cluster_resources().get("GPU", 0):
        pytest.skip("this machine's Ray cluster has a GPU")
    with pytest.raises(RuntimeError, match="asks for 1 GPU"):
        run_jobs([job], RayCluster(), "gpu")
    with pytest.raises(RuntimeError, match="lower --cpus-per-run"):
        run_jobs(_plan(tmp_path), RayCluster(cpus_per_run=3), "cpu")
    assert not Path(job["out"]).exists() and not partial_dir(Path(job["out"])).exists()
