"""The run loop shared by every method: evaluate, update, log, checkpoint, ship.

A *learner* (:class:`medc_training.learner.Learner`) is a :class:`medc_training.ppo.Trainer`
or a :class:`medc_training.frl.FederatedGroup`; both offer ``train_update()``, ``evaluate()``,
``focal`` (the Trainer that is evaluated and shipped), ``side_names()``/``side_evaluate()``
(other users' curves), ``state_dict()``/``load_state_dict()`` and ``global_step``. The loop
checkpoints after every update (``checkpoint.safetensors``, no pickle), so a killed run loses
at most one update when resumed with ``resume=True``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from .bundle import load_state, save_bundle, save_state
from .config import LEGACY_EVAL, TrainConfig
from .learner import check_learner
from .metrics import MetricsLogger

CHECKPOINT = "checkpoint.safetensors"
BUNDLE = "policy.safetensors"


def _progress(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from .console import progress_bar

    return progress_bar(total, initial=initial, unit="step")


def run_training(learner, cfg: TrainConfig, out_dir: str | Path, resume: bool = False, progress: bool = False,
                 tensorboard: bool = True, save_final: bool = True, max_updates: int | None = None,
                 inputs: dict | None = None, overwrite: bool = False) -> dict:
    """Train ``learner`` (a :class:`medc_training.learner.Learner`) to ``cfg.total_steps`` training
    steps, writing everything to ``out_dir``.

    Writes ``metrics.csv`` (one row per evaluation, see medc_training.metrics), ``tb/``
    (TensorBoard events), ``checkpoint.safetensors`` (after every update), and at the end
    ``policy.safetensors`` (the focal learner's bundle), ``learning_curve.png`` and
    ``summary.json``. ``max_updates`` stops early (used to simulate a killed run).
    ``inputs`` (:func:`medc_training.runs.run_inputs`: expert specs and weights, FRL side users)
    is recorded with the config in the checkpoint and the summary.

    A folder holds one run (:mod:`medc_training.runs`): ``resume`` refuses a checkpoint of another
    configuration (every field but ``total_steps`` and ``torch_threads``, and the inputs), naming
    each differing field; without ``resume`` a folder that already holds a run (a summary or a
    checkpoint) is refused unless ``overwrite``; a folder another run is writing is refused
    (:class:`medc_training.runs.RunFolderBusy`, naming its pid). Returns the summary dict.
    """
    from .runs import lock_run_folder

    check_learner(learner)
    out = Path(out_dir)
    with lock_run_folder(out):  # one run at a time in a folder (RunFolderBusy names the holder)
        return _run_locked(learner, cfg, out, resume, progress, tensorboard, save_final, max_updates,
                           inputs, overwrite)


def _run_locked(learner, cfg: TrainConfig, out: Path, resume: bool, progress: bool, tensorboard: bool,
                save_final: bool, max_updates: int | None, inputs: dict | None, overwrite: bool) -> dict:
    """:func:`run_training`'s body, with ``out``'s run lock held."""
    ckpt = out / CHECKPOINT
    next_eval, train_seconds = _open_run_folder(out, learner, cfg, resume, overwrite, inputs)
    logger = MetricsLogger(out, tensorboard=tensorboard,
                           resume_from_step=learner.global_step if resume else None)
    focal = learner.focal
    # FRL can report other users' curves too (e.g. the A3W3 user of the same federation).
    side_loggers: dict[str, MetricsLogger] = {}
    for name in learner.side_names():
        side_loggers[name] = MetricsLogger(out, tensorboard=False, csv_name=f"metrics_{name}.csv",
                                           resume_from_step=learner.global_step if resume else None)
    bar = _progress(cfg.total_steps, learner.global_step, progress)
    last_losses: dict = {}
    sps = math.nan
    updates_done = 0
    # charts/SPS as CleanRL defines it: the steps this process has taken over its wall time since
    # training began (rollouts, updates, evaluations and checkpoints all included).
    started, first_step = time.perf_counter(), learner.global_step
    try:
        while True:
            if learner.global_step >= next_eval or learner.global_step >= cfg.total_steps:
                ev = learner.evaluate()
                row = _metrics_row(learner, ev, sps, train_seconds, last_losses)
                logger.log(row)
                if side_loggers:
                    for name, side_ev in learner.side_evaluate().items():
                        side_loggers[name].log({"step": learner.global_step, "update": focal.updates,
                                                "episode_length": side_ev["episode_length"],
                                                "success_rate": side_ev["success_rate"]})
                if bar is not None:
                    # Shown at the bar's next redraw: a forced one per evaluation would put a line per
                    # evaluation into a log file (console.progress_bar redraws a log once a minute).
                    bar.set_postfix(ep_len=f"{ev['episode_length']:.1f}", success=f"{ev['success_rate']:.2f}",
                                    refresh=False)
                while next_eval <= learner.global_step:
                    next_eval += max(1, cfg.eval_every)
            stop_early = max_updates is not None and updates_done >= max_updates
            if learner.global_step >= cfg.total_steps or stop_early:
                break
            before = learner.global_step
            start = time.perf_counter()
            last_losses = learner.train_update()
            elapsed = time.perf_counter() - start
            train_seconds += elapsed
            wall = time.perf_counter() - started
            sps = (learner.global_step - first_step) / wall if wall > 0 else math.nan
            updates_done += 1
            save_state(ckpt, {"learner": learner.state_dict(), "config": cfg.to_dict(),
                              **({"inputs": inputs} if inputs is not None else {}),
                              "next_eval": next_eval, "train_seconds": train_seconds})
            if bar is not None:
                bar.update(learner.global_step - before)
    finally:
        if bar is not None:
            bar.close()
        logger.close()
        for side in side_loggers.values():
            side.close()
    return _finish_run(out, learner, cfg, row, train_seconds, inputs, save_final)


def _open_run_folder(out: Path, learner, cfg: TrainConfig, resume: bool, overwrite: bool,
                     inputs: dict | None) -> tuple[int, float]:
    """Check that ``out`` may take this run (:func:`run_training`'s rules) and, with ``resume``, load
    its checkpoint into ``learner``. Returns (next evaluation step, training seconds so far)."""
    from .runs import RESUME_FREE, RunMismatch, differences

    ckpt = out / CHECKPOINT
    if not resume and not overwrite and ((out / "summary.json").exists() or ckpt.exists()):
        if _finished(out / "summary.json"):
            raise RunMismatch(f"{out} already holds a finished run (summary.json); give --overwrite to "
                              "replace it, or use another --out")
        raise RunMismatch(f"{out} holds an unfinished run ({CHECKPOINT}); give --resume to carry it on, "
                          "or --overwrite to start afresh")
    out.mkdir(parents=True, exist_ok=True)
    if not resume:
        return 0, 0.0
    if not ckpt.exists():
        raise FileNotFoundError(f"--resume: no checkpoint at {ckpt}; start without --resume")
    state = load_state(ckpt, device=cfg.device)
    # A checkpoint from before eval_episodes existed was evaluated with the legacy window
    # (TrainConfig.from_dict reads it so); one run's curve never mixes two evaluators.
    diffs = differences({**LEGACY_EVAL, **state["config"]}, state.get("inputs"), cfg.to_dict(), inputs,
                        ignore=RESUME_FREE)
    if diffs:
        raise RunMismatch(f"--resume: the checkpoint in {out} was made with another configuration: "
                          f"{'; '.join(diffs)}; resume with its options, or give --overwrite to start "
                          "afresh")
    learner.load_state_dict(state["learner"])
    return int(state["next_eval"]), float(state["train_seconds"])


def _metrics_row(learner, ev: dict, sps: float, train_seconds: float, last_losses: dict) -> dict:
    """One metrics row: the evaluation ``ev``, the training episodes since the last row, the last
    update's losses."""
    focal = learner.focal
    tr = focal.take_train_stats()
    return {
        "step": learner.global_step, "update": focal.updates,
        "episode_length": ev["episode_length"], "success_rate": ev["success_rate"],
        "episode_return": ev.get("episode_return", math.nan),
        # No training episode finished since the last row: nothing to report (never a placeholder).
        "train_episode_length": tr["episode_length"] if tr.get("episodes") else math.nan,
        "train_success_rate": tr["success_rate"] if tr.get("episodes") else math.nan,
        "train_episode_return": tr["episode_return"] if tr.get("episodes") else math.nan,
        "expert_follow_rate": tr["expert_follow_rate"], "expert_top_rate": tr["expert_top_rate"],
        "expert_step_fraction": tr["expert_step_fraction"],
        "sps": sps, "wall_time": train_seconds, **last_losses,
    }


def _finish_run(out: Path, learner, cfg: TrainConfig, row: dict, train_seconds: float, inputs: dict | None,
                save_final: bool) -> dict:
    """Write the bundle and learning curve (a run that reached its budget) and summary.json from the
    last metrics ``row``; return the summary."""
    focal = learner.focal
    summary = {
        "config": cfg.to_dict(),
        **({"inputs": inputs} if inputs is not None else {}),
        "steps": learner.global_step,
        "updates": focal.updates,
        "train_seconds": train_seconds,
        "final_episode_length": row["episode_length"],
        "final_success_rate": row["success_rate"],
    }
    if save_final and learner.global_step >= cfg.total_steps:
        manifest = bundle_manifest(focal, cfg, {"mean_episode_length": row["episode_length"],
                                                "success_rate": row["success_rate"]})
        save_bundle(out / BUNDLE, focal.net, manifest)
        summary["bundle"] = BUNDLE
        try:
            from .plots import plot_learning_curve

            plot_learning_curve(out / "metrics.csv", out / "learning_curve.png",
                                title=f"{cfg.env} A{cfg.agents}W{cfg.walls} {cfg.method}",
                                greedy=cfg.eval_greedy)
            summary["learning_curve"] = "learning_curve.png"
        except Exception as exc:  # a plotting failure must not lose a finished run
            summary["learning_curve_error"] = str(exc)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _finished(summary: Path) -> bool:
    """Whether ``summary`` is the summary of a run that reached its total_steps."""
    try:
        data = json.loads(summary.read_text())
        return int(data["steps"]) >= int(data["config"]["total_steps"])
    except (OSError, ValueError, KeyError, TypeError):
        return False


def observation_section(env) -> dict:
    """``{"observation": {"name": ...}}`` for a bundle's manifest: always for an application whose
    manifests name their view (``Application.manifest_names_view``), for the others only when
    they do not take 'maps'."""
    from .envs import APPLICATIONS

    name = getattr(env, "observation_name", "maps")
    app = APPLICATIONS.get(getattr(env, "name", None))
    keep = name != "maps" or (app is not None and app.manifest_names_view)
    return {"observation": {"name": name}} if keep else {}


def bundle_manifest(trainer, cfg: TrainConfig, metrics: dict) -> dict:
    """The manifest of a trained policy bundle (provenance and evaluation metrics)."""
    env_attrs = dict(getattr(trainer.env, "attributes", None) or cfg.env_attributes())
    return {
        "application": cfg.env,
        "description": f"{cfg.method} policy for {cfg.env} "
                       + ", ".join(f"{k}={v}" for k, v in env_attrs.items()),
        "environment": env_attrs,
        **observation_section(trainer.env),
        "training": {"method": cfg.method, "steps": int(trainer.global_step), "seed": cfg.seed,
                     "arch": cfg.arch, "horizon": cfg.horizon, "epochs": cfg.epochs,
                     "evaluation": cfg.evaluation,
                     **({"init_from": trainer.init_from} if getattr(trainer, "init_from", None) else {})},
        "metrics": {k: float(v) for k, v in metrics.items()},
    }
