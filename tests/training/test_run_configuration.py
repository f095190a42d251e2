"""a run folder holds one configuration. Resume and "already done" compare all
of it (config and inputs) and refuse a mismatch naming the fields; a finished run is replaced
only with an explicit --overwrite; the committed docs/reproduction runs still count as done."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from medc_training.bundle import load_state
from medc_training.config import TrainConfig
from medc_training.engines import LocalPool, run_jobs
from medc_training.jobs import SUMMARY, job_done
from medc_training.ppo import Trainer
from medc_training.runner import CHECKPOINT, run_training
from medc_training.runs import RunMismatch, run_inputs

TINY = dict(env="target_localization", agents=2, walls=0, grid=7, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_every=64, eval_steps=16, eval_envs=4, eval_episodes=4, seed=3)
TINY_ARGS = ["--agents", "2", "--walls", "0", "--grid", "7", "--max-steps", "12", "--num-envs", "4",
             "--horizon", "32", "--epochs", "1", "--eval-every", "64", "--eval-steps", "16",
             "--eval-envs", "4", "--eval-episodes", "4", "--quiet", "--no-tensorboard", "--threads", "1"]


def test_a_killed_run_resumes_only_under_its_own_configuration(tmp_path):
    cfg = TrainConfig(total_steps=96, observation="maps", **TINY)
    inputs = run_inputs()
    run_training(Trainer(cfg), cfg, tmp_path, tensorboard=False, max_updates=1, inputs=inputs)
    assert load_state(tmp_path / CHECKPOINT)["inputs"] == inputs
    # The three: --lr, --max-steps, --observation (same shape: the full-grid window).
    changed = TrainConfig(total_steps=96, **{**TINY, "max_steps": 20}, lr=1e-3, observation="ego3")
    assert changed.make_options()  # a valid config, and the same observation shape on a 7x7 grid
    with pytest.raises(RunMismatch) as info:
        run_training(Trainer(changed), changed, tmp_path, resume=True, tensorboard=False, inputs=inputs)
    message = str(info.value)
    for field in ("lr=0.0003 recorded vs 0.001 now", "max_steps=12 recorded vs 20 now",
                  "observation='maps' recorded vs 'ego3' now"):
        assert field in message, message
    assert "total_steps" not in message and "--overwrite" in message
    # The inputs are part of the run: an expert added on resume is refused too.
    with pytest.raises(RunMismatch, match=r"experts=\[\] recorded vs \['random'\] now"):
        run_training(Trainer(cfg), cfg, tmp_path, resume=True, tensorboard=False,
                     inputs=run_inputs(["random"]))
    # The same config carries on, to another step count if asked (the steps before are the same).
    longer = TrainConfig(**{**cfg.to_dict(), "total_steps": 128, "torch_threads": 1})
    assert run_training(Trainer(longer), longer, tmp_path, resume=True, tensorboard=False,
                        inputs=inputs)["steps"] == 128


def test_a_finished_or_unfinished_run_is_never_replaced_without_overwrite(tmp_path):
    cfg = TrainConfig(total_steps=64, **TINY)
    run_training(Trainer(cfg), cfg, tmp_path / "a", tensorboard=False, max_updates=1)
    with pytest.raises(RunMismatch, match=r"holds an unfinished run .*--resume.*--overwrite"):
        run_training(Trainer(cfg), cfg, tmp_path / "a", tensorboard=False)
    first = run_training(Trainer(cfg), cfg, tmp_path / "b", tensorboard=False)
    before = (tmp_path / "b" / SUMMARY).read_text()
    other = TrainConfig(total_steps=64, **{**TINY, "seed": 4})
    with pytest.raises(RunMismatch, match=r"already holds a finished run .*--overwrite"):
        run_training(Trainer(other), other, tmp_path / "b", tensorboard=False)
    assert (tmp_path / "b" / SUMMARY).read_text() == before
    replaced = run_training(Trainer(other), other, tmp_path / "b", tensorboard=False, overwrite=True)
    assert replaced["config"]["seed"] == 4 and first["config"]["seed"] == 3
    assert json.loads((tmp_path / "b" / SUMMARY).read_text())["config"]["seed"] == 4


def _job(out: Path, config: dict | None = None, **changes) -> dict:
    cfg = TrainConfig(**{**TINY, "total_steps": 64, **(config or {})}).to_dict()
    return {"name": "run/seed0", "config": cfg, "experts": [], "out": str(out), **changes}


def test_a_sweep_rerun_with_another_method_or_step_count_is_not_already_done(tmp_path, capsys):
    out = tmp_path / "runs" / "run" / "seed0"
    job = _job(out)
    assert len(run_jobs([job], LocalPool(1), "t")) == 1
    assert job_done(job)
    stamp = (out / SUMMARY).stat().st_mtime_ns
    for changes, fields in ((dict(config={"method": "rs"}), ["method='sparse' recorded vs 'rs' now"]),
                            (dict(config={"total_steps": 96}), ["total_steps=64 recorded vs 96 now"]),
                            (dict(config={"method": "medc"}, experts=["random"]),
                             ["method='sparse' recorded vs 'medc' now",
                              "experts=[] recorded vs ['random'] now"])):
        other = _job(out, **changes)
        with pytest.raises(RunMismatch) as info:
            run_jobs([other], LocalPool(1), "t")
        assert all(f in str(info.value) for f in fields), str(info.value)
        assert "--overwrite" in str(info.value)
    assert (out / SUMMARY).stat().st_mtime_ns == stamp  # nothing was replaced
    # torch_threads is not the run's configuration
    assert job_done(_job(out, config={"torch_threads": 1}))
    # With overwrite the other configuration runs and replaces it.
    other = _job(out, config={"total_steps": 96}, overwrite=True)
    assert len(run_jobs([other], LocalPool(1), "t")) == 1
    assert json.loads((out / SUMMARY).read_text())["steps"] == 96 and job_done(other)


def test_medc_train_sweep_and_single_run_refuse_another_configuration(tmp_path, capsys):
    from medc_training.cli.train import main

    out = tmp_path / "sweep"
    assert main([*TINY_ARGS, "--steps", "64", "--seeds", "1", "--jobs", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main([*TINY_ARGS, "--steps", "96", "--seeds", "1", "--jobs", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "total_steps=64 recorded vs 96 now" in err and "--overwrite" in err
    assert main([*TINY_ARGS, "--steps", "96", "--seeds", "1", "--jobs", "1", "--out", str(out),
                 "--overwrite"]) == 0
    assert json.loads((out / "seed-1" / SUMMARY).read_text())["steps"] == 96
    single = tmp_path / "single"
    assert main([*TINY_ARGS, "--steps", "64", "--out", str(single)]) == 0
    assert main([*TINY_ARGS, "--steps", "64", "--lr", "0.001", "--out", str(single)]) == 2
    assert "already holds a finished run" in capsys.readouterr().err
    assert main([*TINY_ARGS, "--steps", "64", "--lr", "0.001", "--out", str(single), "--resume"]) == 2
    assert "lr=0.0003 recorded vs 0.001 now" in capsys.readouterr().err
    assert json.loads((single / SUMMARY).read_text())["config"]["lr"] == 0.0003


def test_the_committed_reproduction_runs_still_count_as_done():
    """docs/reproduction's summaries (recorded before inputs were) match the committed plan."""
    from medc_lab.catalogue import PHASES
    from medc_lab.plan import Plan

    root = Path("docs/reproduction")
    done = set()
    for long_steps in (200_000, 1_000_000, 2_000_000):
        for seeds in (2, 3, 4):
            plan = Plan("cpu", seeds, root, Path("models"), {"long_steps": long_steps}, other_seeds=2)
            for phase in PHASES[1:]:
                done.update(job["out"] for job in plan.jobs(phase) if job_done(job))  # never raises
    assert len(done) >= 90
