"""A reproduction: the phases' jobs run on an engine, then the report rebuilt from the runs."""

from __future__ import annotations

import time
from pathlib import Path

from medc_training.engines import run_jobs

from .catalogue import PHASES
from .plan import Plan

#: Phases of fleet coordination and maze cleaning (skipped with other_apps=False).
OTHER_APP_PHASES = ("fig10", "long-other")


def record_command(out: Path, command: str, report_only: bool) -> str:
    """Add ``command`` to OUT/command.txt (the first full command plus any later ones that added
    runs) and return what the report's "Made by" shows: for a report rebuilt without training,
    the recorded commands and the rebuilding one."""
    record = out / "command.txt"
    if not report_only:
        lines = record.read_text().splitlines() if record.exists() else []
        if command not in lines:
            record.write_text("\n".join([*lines, command]) + "\n")
    elif record.exists():  # a rebuilt report names the command that made its runs
        command = record.read_text().strip() + f"\n# report rebuilt with: {command}"
    return command


def reproduce(plan: Plan, phases, engine, retrain: bool = False, other_apps: bool = True,
              overwrite: bool = False) -> dict[str, float]:
    """Run the jobs of ``phases`` (experts first, then every experiment run once, the longest
    first) on ``engine``; returns the wall time of each stage in seconds. A run folder holding a
    finished run of another configuration is refused (RunMismatch, naming the fields) unless
    ``overwrite``: then it is run again and replaced."""
    elapsed: dict[str, float] = {}

    def timed(name: str, jobs: list[dict]) -> None:
        t0 = time.time()
        run_jobs(jobs, engine, name)
        elapsed[name] = time.time() - t0

    if "experts" in phases:
        jobs = plan.expert_jobs(retrain)
        if other_apps:
            jobs += plan.other_expert_jobs(retrain)
        timed("experts", jobs)
    runs: list[dict] = []
    for phase in PHASES[1:]:
        if phase in phases and (other_apps or phase not in OTHER_APP_PHASES):
            runs += plan.jobs(phase)
    if runs:
        unique = {j["out"]: {**j, "overwrite": overwrite} for j in runs}  # sparse baselines are shared
        # the longest jobs first so the pool's tail is short
        timed("experiments", sorted(unique.values(), key=lambda j: -len(j["config"].get("frl_users") or [0])))
    return elapsed
