"""The job plan: the runs of a phase's figure (see :mod:`.figures`) for one scale and output folder,
and the DAgger jobs that train the experts. Planning only reads; :mod:`.jobs` runs the jobs.

The evaluator of a plan's runs follows its output folder, so that one report never mixes two:
a folder whose finished runs were evaluated with the legacy window (``eval_episodes`` 0, or
recorded before the field existed, as the committed docs/reproduction) gets window runs, written
with ``eval_episodes: 0`` in their configs; any other folder gets the fixed-episode evaluator
(:func:`medc_training.evaluate.play_episodes`).
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict
from pathlib import Path

from medc_training.envs.names import DEFAULT_APPLICATION

from .catalogue import (
    BUDGETS,
    OTHER_APPS,
    OTHER_EVAL,
    OTHER_GRID,
    OTHER_MAX_STEPS,
    SCOPES,
    TL_EXPERTS,
    long_tag,
)
from .figures import FIGURES, TAGGED, Figure, Run


def window_evaluated(runs: Path) -> bool:
    """Whether the finished runs under ``runs`` (``<name>/seed<k>/summary.json``) were evaluated
    with the legacy window (False when there are none). Raises ValueError when some were and
    some were not: such a folder's report would compare numbers of two evaluators."""
    from medc_training.config import TrainConfig

    kinds: dict[bool, str] = {}
    for summary in sorted(runs.glob("*/seed*/summary.json")):
        config = json.loads(summary.read_text()).get("config", {})
        kinds.setdefault(TrainConfig.from_dict(config).eval_episodes == 0, str(summary.parent))
    if len(kinds) > 1:
        raise ValueError(f"{runs} mixes evaluators: {kinds[True]} was evaluated with the legacy window "
                         f"(eval_episodes 0), {kinds[False]} with fixed episodes; keep them in separate "
                         "--out folders")
    return kinds.get(True, False)


class Plan:
    """Builds the job list of each phase for one scale and output folder (see the module's note
    on which evaluator its runs get)."""

    def __init__(self, scale: str, seeds: int, out: Path, models: Path, budget: dict | None = None,
                 other_seeds: int | None = None, device: str = "cpu", apps=None) -> None:
        from medc_training.config import LEGACY_EVAL, scaled_config

        self.scale, self.seeds, self.out, self.models = scale, seeds, out, models
        #: What this scale's reproduction covers (seeds, panels, team, applications).
        self.scope = SCOPES[scale]
        #: Fleet coordination / maze cleaning applications whose experts and runs are planned.
        self.apps = tuple(OTHER_APPS) if apps is None else tuple(apps)
        if not self.scope.other_apps:
            self.apps = ()
        unknown = set(self.apps) - set(OTHER_APPS)
        if unknown:
            raise ValueError(f"unknown application(s) {sorted(unknown)}; choose from {sorted(OTHER_APPS)}")
        self.other_seeds = seeds if other_seeds is None else other_seeds
        self.budget = dict(BUDGETS[scale])
        self.budget.update({k: v for k, v in (budget or {}).items() if v})
        self.base = scaled_config(scale, device=device).to_dict()
        #: The runs keep the legacy window evaluator of the runs already in ``out``.
        self.window_eval = window_evaluated(out / "runs")
        if self.window_eval:
            self.base.update(LEGACY_EVAL)

    def cfg(self, **overrides) -> dict:
        return {**self.base, **overrides}

    def expert_path(self, name: str) -> str:
        return str(self.models / "experts" / f"{name}.safetensors")

    def figure(self, phase: str) -> Figure:
        """The figure declaration of ``phase`` at this plan's budget."""
        if phase in TAGGED:
            return FIGURES[phase](long_tag(self.budget["long_steps"]))
        return FIGURES[phase]()

    def seed_range(self, count: int) -> range:
        """The seeds of a run planned ``count`` times: from the scope's first seed on."""
        return range(self.scope.first_seed, self.scope.first_seed + count)

    def planned(self, run: Run) -> bool:
        """Whether ``run`` is in this plan's scope (its application, its number of walls)."""
        if run.env in OTHER_APPS:
            return run.env in self.apps
        return self.scope.walls is None or run.walls in self.scope.walls

    def jobs(self, phase: str) -> list[dict]:
        """One job per run of the phase's figure and seed (none of the sweep's outside a scope
        that plans it: see Scope.sweep)."""
        if phase == "sweep" and not self.scope.sweep:
            return []
        fig = self.figure(phase)
        seeds = self.seeds if fig.seeds == "seeds" else self.other_seeds
        if fig.max_seeds is not None:
            seeds = min(seeds, fig.max_seeds)
        steps = self.budget[fig.steps]
        runs = [r for r in fig.runs() if self.planned(r)]
        return [self.job(fig.phase, run, seed, steps) for seed in self.seed_range(seeds) for run in runs]

    def job(self, fig: str, run: Run, seed: int, steps: int) -> dict:
        cfg = self.run_config(run, seed, steps)
        experts = [re.sub(r"@(.+)$", lambda m: self.expert_path(m.group(1)), e) for e in run.experts]
        return {"name": f"{run.name}/seed{seed}", "fig": fig, "config": cfg, "experts": experts,
                "side_users": list(run.side_users), "out": str(self.out / "runs" / run.name / f"seed{seed}")}

    def run_config(self, run: Run, seed: int, steps: int) -> dict:
        """The TrainConfig (as a dict) of one seed of ``run`` with ``steps`` training steps, the
        run's own ``options`` over the scale's (a field the config does not have is refused)."""
        if run.env not in OTHER_APPS:
            cfg = self.cfg(env=run.env, agents=run.agents, walls=run.walls, method=run.method,
                           total_steps=steps, seed=seed)
        else:
            cfg = self.cfg(env=run.env, agents=run.agents, walls=run.walls,
                           env_options=OTHER_APPS[run.env]["target"], total_steps=steps, seed=seed,
                           max_steps=OTHER_MAX_STEPS, grid=OTHER_GRID, **self.other_eval(), method=run.method)
        if run.frl_users:
            cfg["frl_users"] = [dict(u) for u in run.frl_users]
        if run.max_evals:
            cfg["eval_every"] = max(cfg["eval_every"], steps // run.max_evals)
        unknown = [k for k, _ in run.options if k not in cfg]
        if unknown:
            raise ValueError(f"run {run.name}: {unknown} are not TrainConfig fields")
        cfg.update(run.options)
        return cfg

    def other_eval(self) -> dict:
        """Fleet/maze evaluation settings (sampled actions; see OTHER_EVAL). At the paper scale
        they are evaluated at the paper's interval; at the CPU scale, where one evaluation
        (up to 12,800 steps; 6,400 with the window) would outweigh 4,096 training steps, about six
        times per run."""
        from medc_training.config import LEGACY_EVAL

        every = self.base["eval_every"]
        if self.scale == "cpu":
            every = max(every, self.budget["fleet_maze_steps"] // 6)
        return {**OTHER_EVAL, "eval_every": every, **(LEGACY_EVAL if self.window_eval else {})}

    # experts and the shipped team are DAgger clones of the scripted oracle (medc_training.dagger)
    def expert_jobs(self, retrain: bool) -> list[dict]:
        jobs = []
        steps = self.budget["expert_steps"]
        for name, agents, walls, arch in TL_EXPERTS:
            jobs.append(self._expert_job(name, DEFAULT_APPLICATION, agents, arch, steps, retrain,
                                         walls=walls))
        if self.scope.team:
            jobs.append(self._expert_job("A3W2", DEFAULT_APPLICATION, 3, "mlp", self.budget["team_steps"],
                                         retrain, walls=2, folder="team"))
        return [j for j in jobs if j is not None]

    def other_expert_jobs(self, retrain: bool) -> list[dict]:
        jobs = []
        for app in self.apps:
            for i, (name, agents, options) in enumerate(OTHER_APPS[app]["experts"]):
                arch = "lenet5" if i == 1 else "mlp"
                jobs.append(self._expert_job(name, app, agents, arch, self.budget["expert_steps"],
                                             retrain, env_options=options, max_steps=OTHER_MAX_STEPS,
                                             grid=OTHER_GRID, greedy=False))
        return [j for j in jobs if j is not None]

    def _expert_job(self, name, env, agents, arch, steps, retrain, walls=0, env_options=None,
                    folder="experts", max_steps=None, grid=None, greedy=True):
        """A DAgger job for one bundle, or None when a DAgger bundle for the same grid and step
        limit is already there (bundles made any other way are retrained). The bundle is what
        marks a clone job done: a planned one always runs, and replaces its old training folder."""
        from medc_training.bundle import BundleError, manifest_observation, manifest_sensing, read_manifest
        from medc_training.dagger import CloneConfig
        from medc_training.envs import application
        from medc_training.envs.tl_sensing import parse_sensing

        app = application(env)
        target = self.models / folder / f"{name}.safetensors"
        grid, max_steps = grid or self.base["grid"], max_steps or self.base["max_steps"]
        sensing = None
        if app.sensing_presets:  # the scale's sensing preset
            env_options = {**self.base["env_options"], **(env_options or {})}
            sensing = parse_sensing(env_options.get("sensing", app.default_sensing)).name
        if target.exists() and not retrain:
            try:
                manifest = read_manifest(target)
                if app.observation_in_config:
                    wanted = self.base["observation"] or app.default_observation
                else:  # an env option, its default the application's
                    wanted = (env_options or {}).get("observation", app.default_observation)
                same = (manifest["environment"].get("grid") == grid
                        and (sensing is None or manifest_sensing(manifest) == sensing)
                        and (manifest_observation(manifest) or "maps") == wanted
                        and manifest.get("environment", {}).get("max_steps") == max_steps
                        and manifest.get("training", {}).get("method") == "dagger")
                if same:
                    return None
            except (BundleError, KeyError):
                pass
        cfg = CloneConfig(env=env, agents=agents, walls=walls, grid=grid, max_steps=max_steps,
                          observation=self.base["observation"],
                          env_options=env_options or {}, arch=arch, total_steps=steps,
                          seed=1000 + len(name) * 7 + agents, eval_greedy=greedy,
                          device=self.base["device"]).validate()
        out = self.out / "expert-training" / name
        return {"name": f"expert {name}", "fig": "experts", "kind": "clone", "config": asdict(cfg),
                "out": str(out), "bundle_to": str(target)}
