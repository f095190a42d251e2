"""Jobs: one training run (or one expert's DAgger cloning) as a plain dict, run atomically.

A job is ``{"name", "out", "config", ...}`` (see :meth:`.plan.Plan.job`); ``kind: "clone"``
marks a DAgger job. :func:`run_job` trains in a hidden sibling folder ``.<run>.partial/`` and
renames it to ``out`` only when the run has finished, so ``out`` either holds a finished run
(its ``summary.json``) or does not exist: an interrupted run leaves nothing half-written where the
report reads, and a rerun picks the unfinished one up from the checkpoint in its partial folder.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

SUMMARY = "summary.json"


def check_experts(method: str, expert_specs, expert_weights=None) -> None:
    """Refuse experts given to a method that does not use them, and expert weights given without
    experts (a clear error, not silence)."""
    if expert_weights is not None and not expert_specs:
        raise ValueError("expert weights were given without experts: give one --expert per weight")
    if not expert_specs:
        return
    if method == "frl":
        raise ValueError("experts are not used by method frl (FRL shares parameters, not actions)")
    if method not in ("medc", "il"):
        raise ValueError(f"experts are only used by method medc or il, not {method}")


def make_learner(cfg, expert_specs=(), expert_weights=None, side_users=()):
    """The learner a config describes: a Trainer with its experts parsed from their specs
    (medc_training.experts.parse_expert) and their R_S (``expert_weights``, one per spec; None =
    from the QoS rule, see medc_training.qos), or an FRL group (``side_users``: indices of users
    whose own evaluation curves are logged too)."""
    import torch

    from .experts import parse_expert
    from .ppo import Trainer

    check_experts(cfg.method, expert_specs, expert_weights)
    if cfg.method == "frl":
        from .frl import FederatedGroup

        return FederatedGroup(cfg, side_users=tuple(side_users))
    gen = torch.Generator().manual_seed(cfg.seed + 13)
    return Trainer(cfg, [parse_expert(s, generator=gen, device=cfg.device) for s in expert_specs],
                   expert_weights)


def partial_dir(out: Path) -> Path:
    """Where an unfinished run of ``out`` lives until it finishes."""
    return out.parent / f".{out.name}.partial"


def job_done(job: dict) -> bool:
    """A training job is done when its run folder holds the summary of the same run: its config
    and inputs (experts, their weights, side users), every field compared
    (:mod:`medc_training.runs`; a summary recorded before inputs were, like the committed
    docs/reproduction runs, compares its config). A clone job is planned only when its bundle is
    missing or stale (Plan._expert_job), so a planned one is never done.

    Raises:
        RunMismatch: the folder holds a finished run of another configuration (the message names
        the fields), unless the job says ``overwrite``: then it is not done, and running it
        replaces that run.
    """
    from .runs import RunMismatch, check_finished, job_inputs

    summary = Path(job["out"]) / SUMMARY
    if job.get("kind") == "clone" or not summary.exists():
        return False
    try:
        return check_finished(json.loads(summary.read_text()), job["config"], job_inputs(job), job["out"])
    except RunMismatch:
        if job.get("overwrite"):
            return False
        raise


def run_job(job: dict) -> dict:
    """Run one job (in whatever process an engine gives it); returns its summary."""
    out = Path(job["out"])
    if job_done(job):
        return json.loads((out / SUMMARY).read_text())
    work = partial_dir(out)
    if job.get("kind") == "clone":
        from .dagger import BUNDLE, CloneConfig, clone_oracle

        shutil.rmtree(work, ignore_errors=True)  # DAgger has no checkpoint to resume from
        summary = clone_oracle(CloneConfig.from_dict(job["config"]), work, bundle_to=job["bundle_to"])
        (work / BUNDLE).unlink(missing_ok=True)  # the bundle lives in models/; keep the report folder small
    else:
        summary = _train(job, out, work)
    if out.exists():
        shutil.rmtree(out)
    work.rename(out)
    return summary


def _train(job: dict, out: Path, work: Path) -> dict:
    from .config import TrainConfig
    from .runner import CHECKPOINT, run_training

    if out.exists() and not work.exists() and not (out / SUMMARY).exists():
        out.rename(work)  # an unfinished run left in place by an older version
    # A finished run of another config (replaced with overwrite) stays until the new one finishes.
    from .runs import RunFolderBusy, job_inputs

    cfg = TrainConfig.from_dict(job["config"]).validate()
    learner = make_learner(cfg, job.get("experts", ()), job.get("expert_weights"), job.get("side_users", ()))
    options = {"tensorboard": job.get("tensorboard", False), "save_final": job.get("save_final", False),
               "inputs": job_inputs(job)}
    resume = (work / CHECKPOINT).exists()
    try:
        summary = run_training(learner, cfg, work, resume=resume, overwrite=True, **options)
    except RunFolderBusy:  # another sweep is running this job: never start it afresh under it
        raise
    except ValueError:  # a checkpoint of another config, or an unreadable one: start afresh
        if not resume:
            raise
        learner = make_learner(cfg, job.get("experts", ()), job.get("expert_weights"),
                               job.get("side_users", ()))
        summary = run_training(learner, cfg, work, resume=False, overwrite=True, **options)
    if not job.get("keep_checkpoint", False):
        (work / CHECKPOINT).unlink(missing_ok=True)  # keep the report folder small
    return summary
