"""A killed run resumes from its last checkpoint (at most one update lost) and carries on."""

import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from medc_training.bundle import load_state, read_manifest
from medc_training.config import TrainConfig
from medc_training.metrics import read_metrics
from medc_training.ppo import Trainer
from medc_training.runner import CHECKPOINT, run_training

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_every=32, eval_steps=16, eval_envs=4, eval_episodes=4, seed=3)


def test_resume_continues_from_the_checkpointed_step(tmp_path):
    cfg = TrainConfig(total_steps=160, **TINY)
    run_training(Trainer(cfg), cfg, tmp_path, tensorboard=False, max_updates=2)  # "killed" after 2 updates
    state = load_state(tmp_path / CHECKPOINT)
    assert state["learner"]["global_step"] == 64 and state["learner"]["updates"] == 2

    resumed = Trainer(cfg)
    summary = run_training(resumed, cfg, tmp_path, resume=True, tensorboard=False)
    assert summary["steps"] == 160 and summary["updates"] == 5
    steps = [int(r["step"]) for r in read_metrics(tmp_path / "metrics.csv")]
    assert steps == sorted(set(steps)), "each evaluation step appears once, in order"
    assert steps[0] == 0 and steps[-1] == 160 and 64 in steps


def test_resume_restores_weights_and_optimizer(tmp_path):
    cfg = TrainConfig(total_steps=96, **TINY)
    first = Trainer(cfg)
    run_training(first, cfg, tmp_path, tensorboard=False, max_updates=1)
    second = Trainer(TrainConfig(**{**cfg.to_dict(), "seed": cfg.seed}))
    state = load_state(tmp_path / CHECKPOINT)
    second.load_state_dict(state["learner"])
    for a, b in zip(first.net.state_dict().values(), second.net.state_dict().values()):
        assert torch.equal(a, b)
    steps = [t.optimizer.state_dict()["state"][0]["step"] for t in (first, second)]
    assert steps[0] == steps[1]


def test_resume_rejects_a_different_run(tmp_path):
    cfg = TrainConfig(total_steps=64, **TINY)
    run_training(Trainer(cfg), cfg, tmp_path, tensorboard=False, max_updates=1)
    other = TrainConfig(total_steps=64, **{**TINY, "agents": 1})
    try:
        run_training(Trainer(other), other, tmp_path, resume=True, tensorboard=False)
    except ValueError as exc:
        assert "agents" in str(exc)
    else:
        raise AssertionError("resuming with another team size must fail")


def test_resume_rejects_another_evaluator(tmp_path):
    """One run's learning curve never mixes two evaluators; a checkpoint written before
    eval_episodes existed counts as the legacy window (the harness's evaluator)."""
    import medc_lab.window  # noqa: F401  (registers the window evaluator)
    from medc_training.bundle import save_state

    cfg = TrainConfig(total_steps=64, **TINY)
    assert cfg.eval_episodes > 0
    run_training(Trainer(cfg), cfg, tmp_path, tensorboard=False, max_updates=1)
    window = TrainConfig(total_steps=64, **{**TINY, "eval_episodes": 0})
    with pytest.raises(ValueError, match="eval_episodes"):
        run_training(Trainer(window), window, tmp_path, resume=True, tensorboard=False)
    state = load_state(tmp_path / CHECKPOINT)
    state["config"] = {k: v for k, v in state["config"].items() if k != "eval_episodes"}
    save_state(tmp_path / CHECKPOINT, state)
    with pytest.raises(ValueError, match="eval_episodes=0"):
        run_training(Trainer(cfg), cfg, tmp_path, resume=True, tensorboard=False)
    assert run_training(Trainer(window), window, tmp_path, resume=True, tensorboard=False)["steps"] == 64


@pytest.mark.timing
def test_cli_run_killed_with_sigkill_resumes(tmp_path):
    out = tmp_path / "run"
    args = [sys.executable, "-m", "medc_training.cli.train", "--agents", "2", "--walls", "0", "--grid", "6",
            "--max-steps", "12", "--num-envs", "4", "--horizon", "32", "--epochs", "1", "--eval-every", "64",
            "--eval-steps", "16", "--steps", "100000", "--seed", "1", "--out", str(out), "--quiet",
            "--no-tensorboard", "--threads", "1"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    ckpt = out / CHECKPOINT
    deadline = time.time() + 90
    try:
        while time.time() < deadline:
            if ckpt.exists() and load_state(ckpt)["learner"]["updates"] >= 2:
                break
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.2)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    saved = load_state(ckpt)["learner"]["global_step"]
    assert saved >= 64
    total = saved + 64
    at = args.index("--steps")
    resume = subprocess.run([*args[:at + 1], str(total), *args[at + 2:], "--resume"],
                            capture_output=True, text=True, timeout=120)
    assert resume.returncode == 0, resume.stderr
    assert load_state(ckpt)["learner"]["global_step"] == total
    steps = [int(r["step"]) for r in read_metrics(out / "metrics.csv")]
    assert steps == sorted(set(steps)) and steps[-1] == total
    assert (out / "policy.safetensors").exists() and (out / "learning_curve.png").exists()
    # the bundle records the evaluator its metrics were measured with (medc-train's default)
    evaluation = read_manifest(out / "policy.safetensors")["training"]["evaluation"]
    assert evaluation == {"evaluator": "episodes", "episodes": TrainConfig().eval_episodes, "envs": 32,
                          "greedy": True}
