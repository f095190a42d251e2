"""`medc-reproduce`: the paper's experiments (Figs. 6-11) at a named scale, several seeds.

    medc-reproduce --scale cpu --seeds 4 --other-seeds 2 --out docs/reproduction
    medc-reproduce --scale cpu --only experts          # (re)train models/experts and models/team

Phases (``--only`` picks some; default all):

- ``experts``: trains the expert bundles the experiments use (models/experts/*.safetensors)
  and the shipped team (models/team/A3W2.safetensors) by DAgger cloning of the scripted
  oracle (medc_training.dagger, as ``medc-clone``). Existing DAgger bundles for the same grid
  and step limit are reused unless ``--retrain``.
- ``fig6``: MEDC with the free (A1W0), complex (A1W3) and combined experts vs MDRL-sparse on
  A3W2 and A3W3.
- ``fig7``: A3W2 with 5 proper / random / biased / malicious experts vs sparse.
- ``fig8``: MEDC (6 experts) vs FRL (8 users) vs RS vs IL on A3W2 and A3W3, with wall time.
- ``fig9``: 8 users of which 3 are faulty: MEDC vs FRL vs IL on A3W2.
- ``fig10``: fleet coordination and maze cleaning, MEDC vs FRL vs IL, truthful (Fig. 10) and
  with 3 faulty experts/users (Fig. 11).

Every run writes OUT/runs/<run>/seed<k>/ (metrics.csv, summary.json); a run whose
summary.json exists is not run again, so a killed reproduction picks up where it stopped.
The figures and OUT/report.md are written at the end from whatever runs exist.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

from ..stats import T95, compare, learning_score, mean_ci, t95  # noqa: F401  (re-exported)

PHASES = ("experts", "fig6", "fig7", "fig8", "fig9", "fig10", "long", "long-other")

# Per-scale budget: training steps of each experiment run, of each expert, of the team.
BUDGETS = {
    "cpu": {"steps": 150_000, "expert_steps": 128_000, "team_steps": 128_000, "fleet_maze_steps": 100_000,
            "long_steps": 200_000},
    "paper": {"steps": 20_000_000, "expert_steps": 2_000_000, "team_steps": 2_000_000,
              "fleet_maze_steps": 20_000_000, "long_steps": 20_000_000},
}

# Target-localization experts: (name, agents, walls, architecture). The paper's 6 FRL/MEDC
# users A1W0, A3W0, A2W1, A2W2, A2W3, A3W1 plus the "complex" A1W3 of Fig. 6. Two
# architectures are mixed on purpose: MEDC only needs actions from its experts. On the default
# agent-centred observation with the source estimate an MLP clones the oracle well (on the
# paper's absolute maps it did not: A3W2, 51k steps of DAgger, greedy 33 steps against
# LeNet-5's 7, random 36), so the MLP is mixed with the paper's LeNet-5.
TL_EXPERTS = (
    ("A1W0", 1, 0, "mlp"),
    ("A1W3", 1, 3, "lenet5"),
    ("A3W0", 3, 0, "mlp"),
    ("A2W1", 2, 1, "lenet5"),
    ("A2W2", 2, 2, "mlp"),
    ("A2W3", 2, 3, "lenet5"),
    ("A3W1", 3, 1, "mlp"),
)
SIX = ("A1W0", "A3W0", "A2W1", "A2W2", "A2W3", "A3W1")        # paper Section V-C, first 6 users
PROPER5 = ("A1W0", "A3W0", "A2W1", "A2W2", "A3W1")            # Fig. 7 "proper experts"
FRL_USERS = ((1, 0), (3, 0), (2, 1), (2, 2), (2, 3), (3, 1), (3, 2), (3, 3))
FAULTY_USERS = {"A2W1": "random", "A2W2": "biased", "A3W1": "malicious"}  # Fig. 9: 3 of the 8

# Fleet coordination and maze cleaning: the paper's 10x10 grid at every scale. The paper gives
# no step limit; 400 lets a uniformly random team finish some episodes (measured on 64
# episodes: maze complexity 1.0 42%, fleet with 8 customers 9%; at 100 steps neither ever
# finishes, and every curve sits flat at the limit). A memoryless greedy policy repeats one
# move forever in these coverage tasks, so they are evaluated on sampled actions, 16
# environments x 400 steps per evaluation.
OTHER_GRID = 10
OTHER_MAX_STEPS = 400
OTHER_EVAL = {"eval_greedy": False, "eval_envs": 16, "eval_steps": 16 * OTHER_MAX_STEPS}

# Fleet coordination / maze cleaning experts: (name, agents, env options); the user of
# interest is 3 agents (fleet: 8 customers; maze: complexity 1.0). "short" prefixes run names.
OTHER_APPS = {
    "fleet_coordination": {
        "short": "fleet",
        "title": "Fleet coordination",
        "target": {"customers": 8},
        "experts": (("fleet-A1C4", 1, {"customers": 4}), ("fleet-A2C4", 2, {"customers": 4}),
                    ("fleet-A2C6", 2, {"customers": 6}), ("fleet-A1C8", 1, {"customers": 8}),
                    ("fleet-A3C4", 3, {"customers": 4}), ("fleet-A2C8", 2, {"customers": 8})),
    },
    "maze_cleaning": {
        "short": "maze",
        "title": "Maze cleaning",
        "target": {"complexity": 1.0},
        "experts": (("maze-A1C0", 1, {"complexity": 0.0}), ("maze-A2C0", 2, {"complexity": 0.0}),
                    ("maze-A1C1", 1, {"complexity": 1.0}), ("maze-A2C1", 2, {"complexity": 1.0}),
                    ("maze-A3C0", 3, {"complexity": 0.0}), ("maze-A2C05", 2, {"complexity": 0.5})),
    },
}


def long_tag(steps: int) -> str:
    """Run-name prefix of a supplementary long run, e.g. long200k."""
    return f"long{steps // 1000}k" if steps % 1_000_000 else f"long{steps // 1_000_000}M"


def long_tags_on_disk(runs: Path, marker: str) -> list[str]:
    """The long_tag prefixes of the runs ``<tag>-<marker>`` under ``runs``, shortest run first."""
    tags = {d.name[: -len(marker) - 1] for d in runs.glob(f"long*-{marker}")}
    return sorted(tags, key=lambda t: float(t[4:-1]) * (1000 if t.endswith("k") else 1_000_000))


# ------------------------------------------------------------------------------ jobs ----
def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)


def run_job(job: dict) -> dict:
    """Run one training job (in a worker process); returns its summary."""
    import torch

    from ..config import TrainConfig
    from ..experts import parse_expert
    from ..frl import FederatedGroup
    from ..ppo import Trainer
    from ..runner import run_training

    out = Path(job["out"])
    if (out / "summary.json").exists():
        return json.loads((out / "summary.json").read_text())
    if job.get("kind") == "clone":
        from ..dagger import BUNDLE, CloneConfig, clone_oracle

        summary = clone_oracle(CloneConfig(**job["config"]), out, bundle_to=job["bundle_to"])
        (out / BUNDLE).unlink(missing_ok=True)  # the bundle lives in models/; keep the report folder small
        return summary
    cfg = TrainConfig.from_dict(job["config"]).validate()
    if cfg.method == "frl":
        learner = FederatedGroup(cfg, side_users=job.get("side_users", ()))
    else:
        gen = torch.Generator().manual_seed(cfg.seed + 13)
        learner = Trainer(cfg, [parse_expert(s, generator=gen, device=cfg.device)
                                for s in job.get("experts", [])], job.get("expert_weights"))
    resume = (out / "checkpoint.safetensors").exists()
    try:
        summary = run_training(learner, cfg, out, resume=resume, tensorboard=False, save_final=False)
    except ValueError:
        if not resume:
            raise
        summary = run_training(learner, cfg, out, resume=False, tensorboard=False, save_final=False)
    (out / "checkpoint.safetensors").unlink(missing_ok=True)  # keep the report folder small
    return summary


def run_jobs(jobs: list[dict], workers: int, label: str) -> None:
    """Run jobs in ``workers`` processes, printing one line per finished job."""
    todo = [j for j in jobs if not (Path(j["out"]) / "summary.json").exists()]
    print(f"[{label}] {len(jobs) - len(todo)} of {len(jobs)} runs already done; running {len(todo)} "
          f"with {workers} worker(s)", flush=True)
    if not todo:
        return
    start = time.time()
    if workers <= 1:
        _worker_init()
        for i, job in enumerate(todo, 1):
            s = run_job(job)
            print(f"  [{i}/{len(todo)}] {job['name']}: final episode length {s['final_episode_length']:.1f} "
                  f"({s['train_seconds']:.0f}s)", flush=True)
        return
    with ProcessPoolExecutor(max_workers=workers, initializer=_worker_init) as pool:
        futures = {pool.submit(run_job, job): job for job in todo}
        for i, fut in enumerate(as_completed(futures), 1):
            job = futures[fut]
            s = fut.result()
            print(f"  [{i}/{len(todo)}] {job['name']}: final episode length {s['final_episode_length']:.1f} "
                  f"({s['train_seconds']:.0f}s, {time.time() - start:.0f}s elapsed)", flush=True)


# --------------------------------------------------------------------------- planning ---
class Plan:
    """Builds the job list of each phase for one scale and output folder."""

    def __init__(self, scale: str, seeds: int, out: Path, models: Path, budget: dict | None = None,
                 other_seeds: int | None = None, device: str = "cpu") -> None:
        from ..config import scaled_config

        self.scale, self.seeds, self.out, self.models = scale, seeds, out, models
        self.other_seeds = seeds if other_seeds is None else other_seeds
        self.budget = dict(BUDGETS[scale])
        self.budget.update({k: v for k, v in (budget or {}).items() if v})
        self.base = scaled_config(scale, device=device).to_dict()

    def cfg(self, **overrides) -> dict:
        return {**self.base, **overrides}

    def expert_path(self, name: str) -> str:
        return str(self.models / "experts" / f"{name}.safetensors")

    def run(self, fig: str, name: str, seed: int, cfg: dict, experts=(), side_users=()) -> dict:
        return {"name": f"{name}/seed{seed}", "fig": fig, "config": cfg, "experts": list(experts),
                "side_users": list(side_users), "out": str(self.out / "runs" / name / f"seed{seed}")}

    # experts and the shipped team are DAgger clones of the scripted oracle (medc_training.dagger)
    def expert_jobs(self, retrain: bool) -> list[dict]:
        jobs = []
        steps = self.budget["expert_steps"]
        for name, agents, walls, arch in TL_EXPERTS:
            jobs.append(self._expert_job(name, "target_localization", agents, arch, steps, retrain,
                                         walls=walls))
        team = self._expert_job("A3W2", "target_localization", 3, "mlp", self.budget["team_steps"],
                                retrain, walls=2, folder="team")
        jobs.append(team)
        return [j for j in jobs if j is not None]

    def other_expert_jobs(self, retrain: bool) -> list[dict]:
        jobs = []
        for app, spec in OTHER_APPS.items():
            for i, (name, agents, options) in enumerate(spec["experts"]):
                arch = "lenet5" if i == 1 else "mlp"
                jobs.append(self._expert_job(name, app, agents, arch, self.budget["expert_steps"],
                                             retrain, env_options=options, max_steps=OTHER_MAX_STEPS,
                                             grid=OTHER_GRID, greedy=False))
        return [j for j in jobs if j is not None]

    def other_eval(self) -> dict:
        """Fleet/maze evaluation settings (sampled actions; see OTHER_EVAL). At the paper scale
        they are evaluated at the paper's interval; at the CPU scale, where one evaluation
        (6,400 steps) would outweigh 4,096 training steps, about six times per run."""
        every = self.base["eval_every"]
        if self.scale == "cpu":
            every = max(every, self.budget["fleet_maze_steps"] // 6)
        return {**OTHER_EVAL, "eval_every": every}

    def _expert_job(self, name, env, agents, arch, steps, retrain, walls=0, env_options=None,
                    folder="experts", max_steps=None, grid=None, greedy=True):
        """A DAgger job for one bundle, or None when a DAgger bundle for the same grid and step
        limit is already there (bundles made any other way are retrained)."""
        from ..bundle import BundleError, manifest_observation, read_manifest
        from ..dagger import CloneConfig

        target = self.models / folder / f"{name}.safetensors"
        grid, max_steps = grid or self.base["grid"], max_steps or self.base["max_steps"]
        if target.exists() and not retrain:
            try:
                manifest = read_manifest(target)
                wanted = self.base["observation"] if env == "target_localization" else None
                same = (manifest["environment"].get("grid") == grid
                        and manifest_observation(manifest) == wanted
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
        if (out / "summary.json").exists():
            (out / "summary.json").unlink()
        return {"name": f"expert {name}", "fig": "experts", "kind": "clone", "config": asdict(cfg),
                "out": str(out), "bundle_to": str(target)}

    def tl(self, fig: str) -> list[dict]:
        steps = self.budget["steps"]
        jobs = []
        for seed in range(self.seeds):
            def add(name, env_walls, method, experts=(), seed=seed, **extra):
                cfg = self.cfg(env="target_localization", agents=3, walls=env_walls, method=method,
                               total_steps=steps, seed=seed, **extra)
                jobs.append(self.run(fig, name, seed, cfg, experts))

            if fig == "fig6":
                for w in (2, 3):
                    add(f"A3W{w}-sparse", w, "sparse")
                    add(f"A3W{w}-medc-free", w, "medc", [self.expert_path("A1W0")])
                    add(f"A3W{w}-medc-complex", w, "medc", [self.expert_path("A1W3")])
                    both = [self.expert_path("A1W0"), self.expert_path("A1W3")]
                    add(f"A3W{w}-medc-combined", w, "medc", both)
            elif fig == "fig7":
                add("A3W2-sparse", 2, "sparse")
                add("A3W2-medc-proper5", 2, "medc", [self.expert_path(n) for n in PROPER5])
                add("A3W2-medc-random5", 2, "medc", ["random"] * 5)
                add("A3W2-medc-biased5", 2, "medc", [f"biased:{a}" for a in (0, 2, 4, 6, 1)])
                add("A3W2-medc-malicious5", 2, "medc", [f"malicious:{self.expert_path(n)}" for n in PROPER5])
            elif fig == "fig8":
                for w in (2, 3):
                    add(f"A3W{w}-sparse", w, "sparse")
                    add(f"A3W{w}-medc-six", w, "medc", [self.expert_path(n) for n in SIX])
                    add(f"A3W{w}-rs", w, "rs")
                    add(f"A3W{w}-il-six", w, "il", [self.expert_path(n) for n in SIX])
                users = [{"agents": a, "walls": w} for a, w in FRL_USERS]
                cfg = self.cfg(env="target_localization", agents=3, walls=2, method="frl", total_steps=steps,
                               seed=seed, frl_users=users)
                jobs.append(self.run(fig, "A3W2-frl8", seed, cfg, side_users=[7]))
            elif fig == "fig9":
                add("A3W2-sparse", 2, "sparse")
                faulty = [self._faulty_spec(n) for n in SIX]
                add("A3W2-medc-six-3faulty", 2, "medc", faulty)
                add("A3W2-il-six-3faulty", 2, "il", faulty)
                users = []
                for a, w in FRL_USERS:
                    user = {"agents": a, "walls": w}
                    if f"A{a}W{w}" in FAULTY_USERS:
                        user["fault"] = FAULTY_USERS[f"A{a}W{w}"]
                    users.append(user)
                cfg = self.cfg(env="target_localization", agents=3, walls=2, method="frl", total_steps=steps,
                               seed=seed, frl_users=users)
                jobs.append(self.run(fig, "A3W2-frl8-3faulty", seed, cfg))
        return jobs

    def long_runs(self) -> list[dict]:
        """Supplement: A3W2 sparse vs MEDC (6 experts) vs MEDC with the scripted oracle as the one
        expert, for ``long_steps`` steps (run names carry the step count), at most 3 seeds."""
        steps = self.budget["long_steps"]
        tag = long_tag(steps)
        jobs = []
        for seed in range(min(self.seeds, 3)):
            base = self.cfg(env="target_localization", agents=3, walls=2, seed=seed, total_steps=steps)
            jobs.append(self.run("long", f"{tag}-A3W2-sparse", seed, {**base, "method": "sparse"}))
            jobs.append(self.run("long", f"{tag}-A3W2-medc-six", seed, {**base, "method": "medc"},
                                 [self.expert_path(n) for n in SIX]))
            jobs.append(self.run("long", f"{tag}-A3W2-medc-oracle", seed, {**base, "method": "medc"},
                                 ["oracle"]))
        return jobs

    def long_other_runs(self) -> list[dict]:
        """Supplement: fleet coordination and maze cleaning, MDRL-sparse vs MEDC vs IL with the
        six experts of Fig. 10, truthful and with 3 faulty (as in Fig. 11), for ``long_steps``
        steps, at most 3 seeds."""
        steps = self.budget["long_steps"]
        tag = long_tag(steps)
        jobs = []
        for app, spec in OTHER_APPS.items():
            short = spec["short"]
            for seed in range(min(self.seeds, 3)):
                base = self.other_base(app, seed, steps)
                base["eval_every"] = max(base["eval_every"], steps // 20)
                sparse = {**base, "method": "sparse"}
                jobs.append(self.run("long-other", f"{tag}-{short}-sparse", seed, sparse))
                for suffix, experts in self.other_expert_sets(spec):
                    for method in ("medc", "il"):
                        jobs.append(self.run("long-other", f"{tag}-{short}-{method}{suffix}", seed,
                                             {**base, "method": method}, experts))
        return jobs

    def other_expert_sets(self, spec: dict) -> tuple[tuple[str, list[str]], ...]:
        """(run-name suffix, expert specs): the six truthful experts of an application, and the
        same six with the first three replaced by a random, a biased and a malicious one."""
        names = [n for n, _, _ in spec["experts"]]
        truthful = [self.expert_path(n) for n in names]
        faulty = ["random", "biased:0", f"malicious:{self.expert_path(names[0])}", *truthful[3:]]
        return ("", truthful), ("-3faulty", faulty)

    def other_base(self, app: str, seed: int, steps: int) -> dict:
        """The config of a fleet/maze run for the user of interest (3 agents, the target options)."""
        return self.cfg(env=app, agents=3, walls=0, env_options=OTHER_APPS[app]["target"], total_steps=steps,
                        seed=seed, max_steps=OTHER_MAX_STEPS, grid=OTHER_GRID, **self.other_eval())

    def _faulty_spec(self, name: str) -> str:
        kind = FAULTY_USERS.get(name)
        if kind == "random":
            return "random"
        if kind == "biased":
            return "biased:0"
        if kind == "malicious":
            return f"malicious:{self.expert_path(name)}"
        return self.expert_path(name)

    def other_apps(self) -> list[dict]:
        steps = self.budget["fleet_maze_steps"]
        jobs = []
        for app, spec in OTHER_APPS.items():
            short = spec["short"]
            for seed in range(self.other_seeds):
                base = self.other_base(app, seed, steps)
                for tag, experts in self.other_expert_sets(spec):
                    for method in ("medc", "il"):
                        jobs.append(self.run("fig10", f"{short}-{method}{tag}", seed,
                                             {**base, "method": method}, experts))
                users = [{"agents": a, "env_options": o} for _, a, o in spec["experts"]]
                users.append({"agents": 3, "env_options": spec["target"]})
                jobs.append(self.run("fig10", f"{short}-frl7", seed,
                                     {**base, "method": "frl", "frl_users": users}))
                bad = [dict(u) for u in users]
                for u, kind in zip(bad[:3], ("random", "biased", "malicious")):
                    u["fault"] = kind
                jobs.append(self.run("fig10", f"{short}-frl7-3faulty", seed,
                                     {**base, "method": "frl", "frl_users": bad}))
                jobs.append(self.run("fig10", f"{short}-sparse", seed, {**base, "method": "sparse"}))
        return jobs


# --------------------------------------------------------------------------- analysis ---
def load_curves(out: Path, name: str, csv_name: str = "metrics.csv"
                ) -> tuple[list[float], list[list[float]], list]:
    """(steps, [episode-length curve per seed], [summary per seed]) of one run name."""
    from ..metrics import read_metrics

    curves, summaries, steps = [], [], []
    for seed_dir in sorted((out / "runs" / name).glob("seed*")):
        if not (seed_dir / "summary.json").exists() or not (seed_dir / csv_name).exists():
            continue
        rows = read_metrics(seed_dir / csv_name)
        if len(rows) > len(steps):
            steps = [r["step"] for r in rows]
        curves.append([r["episode_length"] for r in rows])
        summaries.append(json.loads((seed_dir / "summary.json").read_text()))
    return steps, curves, summaries


#: Seeds the learnability gate needs before it can pass.
GATE_MIN_SEEDS = 3
#: Finished episodes of random play measured per seed for the gate.
GATE_RANDOM_EPISODES = 256


def random_play_length(out: Path, cfg: dict) -> float:
    """Mean episode length of uniformly random valid moves on a run's evaluation episodes (its
    evaluation seed and environment), cached in OUT/random_play.json."""
    from ..config import TrainConfig
    from ..evaluate import evaluate_policy
    from ..ppo import EVAL_SEED_OFFSET, make_env_for

    c = TrainConfig.from_dict(cfg)
    seed = c.seed + EVAL_SEED_OFFSET
    key = (f"{c.env}|agents={c.agents}|walls={c.walls}|grid={c.grid}|max_steps={c.max_steps}|"
           f"{json.dumps(c.env_options, sort_keys=True)}|seed={seed}")
    cache_path = out / "random_play.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if key not in cache:
        env = make_env_for(c, c.eval_envs, seed, False)
        played = evaluate_policy(env, None, GATE_RANDOM_EPISODES, greedy=False, seed=seed)
        cache[key] = played["episode_length"]
        cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return float(cache[key])


def learnability_gate(out: Path, sparse_run: str) -> dict:
    """Did MDRL-sparse learn in ``sparse_run``'s environment? Per seed, its final evaluation episode
    length (mean of the last three evaluations) minus random play's on the same evaluation
    episodes; passed when >= GATE_MIN_SEEDS seeds ran and the 95% CI of the mean difference lies
    entirely below 0. Returns {"passed", "n", "sparse", "random", "diff", "half", "text"}."""
    from ..metrics import read_metrics

    finals, randoms = [], []
    for seed_dir in sorted((out / "runs" / sparse_run).glob("seed*")):
        if not (seed_dir / "summary.json").exists():
            continue
        summary = json.loads((seed_dir / "summary.json").read_text())
        rows = read_metrics(seed_dir / "metrics.csv")
        finals.append(sum(r["episode_length"] for r in rows[-3:]) / len(rows[-3:]))
        randoms.append(random_play_length(out, summary["config"]))
    diffs = [f - r for f, r in zip(finals, randoms)]
    m, half = mean_ci(diffs)
    passed = len(diffs) >= GATE_MIN_SEEDS and m + half < 0
    ms, _ = mean_ci(finals)
    mr, _ = mean_ci(randoms)
    text = (f"MDRL-sparse final episode length {ms:.2f} vs random play {mr:.2f} on the same evaluation "
            f"episodes: difference {m:+.2f} ± {half:.2f} (95% CI, n = {len(diffs)} seeds)")
    return {"passed": passed, "n": len(diffs), "sparse": ms, "random": mr, "diff": m, "half": half,
            "text": text}


def verdict(better: list[float], worse: list[float]) -> str:
    """How the paper's claim "``better`` learns faster than ``worse``" fared (lower learning
    score is better): held / contradicted when the 95% CI of the difference excludes 0, else
    not resolved, saying which way the means lean."""
    if not better or not worse:
        return "not run"
    c = compare(better, worse)
    if c["diff"] == 0:
        return "no difference"
    if c["diff"] + c["half"] < 0:
        return "held"
    if c["diff"] - c["half"] > 0:
        return "contradicted (CI excludes 0 the other way)"
    if c["diff"] < 0:
        return "not resolved (means lean the paper's way; CI includes 0)"
    return "not resolved (means lean against the paper; CI includes 0)"


class Report:
    """Collects figures and claim verdicts into report.md."""

    def __init__(self, out: Path, scale: str, seeds: int, command: str) -> None:
        self.out, self.scale, self.seeds, self.command = out, scale, seeds, command
        self.sections: list[str] = []
        self.scores: dict[str, list[float]] = {}
        #: Learnability gate of each environment, by its MDRL-sparse run name.
        self.gates: dict[str, dict] = {}
        #: The verdict word of every claim written, in order (for the counts).
        self.verdicts: list[str] = []

    def _gate(self, sparse_run: str) -> dict:
        """:func:`learnability_gate` of ``sparse_run``, computed once per report."""
        if sparse_run not in self.gates:
            self.gates[sparse_run] = learnability_gate(self.out, sparse_run)
        return self.gates[sparse_run]

    def gate(self, sparse_run: str) -> str:
        """The gate line for ``sparse_run``'s environment; claims made with ``gate=sparse_run``
        are "not testable" unless it passed."""
        g = self._gate(sparse_run)
        if g["n"] == 0:
            return "- **Learnability gate** — not run"
        word = "passed" if g["passed"] else (
            f"NOT passed (needs >= {GATE_MIN_SEEDS} seeds and a CI below 0): the scale is too small for "
            "MDRL-sparse to learn here, so this environment's claims are not testable")
        return f"- **Learnability gate** ({sparse_run}) — {word}: {g['text']}"

    def _untestable(self, gate: str | None) -> str | None:
        if gate is None:
            return None
        g = self._gate(gate)
        if g["passed"]:
            return None
        return (f"not testable (MDRL-sparse did not pass the learnability gate: difference to random "
                f"play {g['diff']:+.2f} ± {g['half']:.2f}, n = {g['n']})")

    def series(self, names: dict[str, str], csv_name: str = "metrics.csv") -> dict:
        data = {}
        for label, name in names.items():
            steps, curves, summaries = load_curves(self.out, name, csv_name)
            if curves:
                data[label] = (steps, curves, summaries)
                self.scores[name if csv_name == "metrics.csv" else f"{name}:{csv_name}"] = \
                    [learning_score(c) for c in curves]
        return data

    def figure(self, png: str, title: str, names: dict[str, str], csv_name: str = "metrics.csv",
               ylabel: str = "mean episode length (greedy eval)") -> dict:
        from ..plots import plot_methods

        data = self.series(names, csv_name)
        if data:
            plot_methods({k: (v[0], v[1]) for k, v in data.items()}, self.out / png, title, ylabel)
        return data

    def table(self, data: dict, wall: bool = False) -> str:
        head = "| method | seeds | learning score (mean eval ep. length) ± 95% CI | final ep. length ± CI |"
        sep = "|---|---|---|---|"
        if wall:
            head += " train wall time (s) |"
            sep += "---|"
        lines = [head, sep]
        for label, (_, curves, summaries) in data.items():
            m, h = mean_ci([learning_score(c) for c in curves])
            fm, fh = mean_ci([c[-1] for c in curves])
            line = f"| {label} | {len(curves)} | {m:.2f} ± {h:.2f} | {fm:.2f} ± {fh:.2f} |"
            if wall:
                line += f" {sum(s['train_seconds'] for s in summaries) / len(summaries):.1f} |"
            lines.append(line)
        return "\n".join(lines)

    def claim(self, text: str, better: str, worse: str, gate: str | None = None) -> str:
        a, b = self.scores.get(better, []), self.scores.get(worse, [])
        c = compare(a, b) if a and b else {"diff": math.nan, "half": math.nan}
        blocked = self._untestable(gate) if a and b else None
        word = blocked or verdict(a, b)
        self.verdicts.append(word)
        return (f"- **{text}** — {word}: difference of learning scores "
                f"{c['diff']:+.2f} ± {c['half']:.2f} (negative = first is better; n = {len(a)} vs {len(b)})")

    def claim_no_worse(self, text: str, faulty: str, sparse: str, margin: float,
                       gate: str | None = None) -> str:
        a, b = self.scores.get(faulty, []), self.scores.get(sparse, [])
        if not a or not b:
            return f"- **{text}** — not run"
        c = compare(a, b)
        ok = c["diff"] - c["half"] <= margin
        word = "held" if c["diff"] <= margin and ok else ("inconclusive" if ok else "did not hold")
        word = self._untestable(gate) or word
        self.verdicts.append(word)
        return (f"- **{text}** — {word}: {c['diff']:+.2f} ± {c['half']:.2f} episode-length steps vs sparse "
                f"(allowed margin {margin:+.1f}; n = {len(a)} vs {len(b)})")

    def add(self, text: str) -> None:
        self.sections.append(text)

    def verdict_counts(self) -> str:
        """One line counting the claims by verdict (held, contradicted, not resolved, ...)."""
        kinds = ("held", "contradicted", "did not hold", "inconclusive", "not resolved", "not testable",
                 "no difference", "not run")
        counts = {k: sum(v.startswith(k) for v in self.verdicts) for k in kinds}
        return (f"{len(self.verdicts)} claims: " + ", ".join(f"{n} {k}" for k, n in counts.items() if n)
                if self.verdicts else "no claims")

    def write(self, header: str) -> Path:
        path = self.out / "report.md"
        path.write_text(header + "\n\n".join(self.sections) + "\n")
        return path


def expert_table(models: Path) -> str:
    """One row per shipped expert/team bundle: how its DAgger evaluation compares with a random
    team on the same episodes (read from the bundle manifests; empty if there are none)."""
    from ..bundle import BundleError, read_manifest

    rows = []
    for path in [f for d in ("experts", "team") for f in sorted((models / d).glob("*.safetensors"))]:
        try:
            man = read_manifest(path)
            m, t = man["metrics"], man["training"]
            rows.append(f"| {path.parent.name}/{path.stem} | {t['arch']} | {t['method']} {t['steps']:,} | "
                        f"{m['greedy_episode_length']:.1f} ({m['greedy_success_rate']:.0%}) | "
                        f"{m['sampled_episode_length']:.1f} ({m['sampled_success_rate']:.0%}) | "
                        f"{m['random_episode_length']:.1f} ({m['random_success_rate']:.0%}) |")
        except (BundleError, KeyError, TypeError, ValueError):
            rows.append(f"| {path.parent.name}/{path.stem} | ? | no DAgger evaluation in manifest | | | |")
    if not rows:
        return ""
    return ("| bundle | arch | training, steps | greedy: mean ep. length (found) | sampled | random team |\n"
            "|---|---|---|---|---|---|\n" + "\n".join(rows))


def build_report(out: Path, scale: str, seeds: int, command: str, plan: Plan, elapsed: dict) -> Path:
    from ..config import SCALES

    r = Report(out, scale, seeds, command)
    budget = plan.budget
    # --- Fig. 6
    for w in (2, 3):
        data = r.figure(f"fig6_A3W{w}.png", f"Fig. 6: A3W{w}, MEDC experts vs sparse", {
            "MDRL-sparse": f"A3W{w}-sparse", "MEDC free expert (A1W0)": f"A3W{w}-medc-free",
            "MEDC complex expert (A1W3)": f"A3W{w}-medc-complex",
            "MEDC combined experts": f"A3W{w}-medc-combined"})
        if data:
            r.add(f"### Fig. 6 — A3W{w}\n\n![fig6 A3W{w}](fig6_A3W{w}.png)\n\n{r.table(data)}\n\n"
                  + "\n".join([
                r.gate(f"A3W{w}-sparse"),
                r.claim(f"A3W{w}: MEDC free expert beats MDRL-sparse", f"A3W{w}-medc-free", f"A3W{w}-sparse",
                    gate=f"A3W{w}-sparse"),
                r.claim(f"A3W{w}: MEDC complex expert beats MDRL-sparse", f"A3W{w}-medc-complex",
                        f"A3W{w}-sparse", gate=f"A3W{w}-sparse"),
                r.claim(f"A3W{w}: MEDC combined experts beat MDRL-sparse", f"A3W{w}-medc-combined",
                        f"A3W{w}-sparse", gate=f"A3W{w}-sparse"),
                r.claim(f"A3W{w}: the complex expert (A1W3) helps more than the free expert (A1W0)",
                        f"A3W{w}-medc-complex", f"A3W{w}-medc-free", gate=f"A3W{w}-sparse"),
            ]))
    # --- Fig. 7
    data = r.figure("fig7.png", "Fig. 7: A3W2, faulty experts", {
        "MDRL-sparse": "A3W2-sparse", "MEDC 5 proper experts": "A3W2-medc-proper5",
        "MEDC 5 random experts": "A3W2-medc-random5", "MEDC 5 biased experts": "A3W2-medc-biased5",
        "MEDC 5 malicious experts": "A3W2-medc-malicious5"})
    if data:
        margin = 2.0
        r.add("### Fig. 7 — resilience to faulty experts (A3W2)\n\n![fig7](fig7.png)\n\n"
              + r.table(data) + "\n\n"
              + "\n".join([
                r.gate("A3W2-sparse"),
                  r.claim("proper experts beat MDRL-sparse", "A3W2-medc-proper5", "A3W2-sparse",
                      gate="A3W2-sparse"),
                  r.claim_no_worse("random experts: at worst match MDRL-sparse", "A3W2-medc-random5",
                                   "A3W2-sparse", margin, gate="A3W2-sparse"),
                  r.claim_no_worse("biased experts: at worst match MDRL-sparse", "A3W2-medc-biased5",
                                   "A3W2-sparse", margin, gate="A3W2-sparse"),
                  r.claim_no_worse("malicious experts: at worst match MDRL-sparse", "A3W2-medc-malicious5",
                                   "A3W2-sparse", margin, gate="A3W2-sparse"),
              ]) + f"\n\n'At worst match' is judged with a margin of {margin} steps of mean episode length: "
              "held if the faulty run's mean is within the margin, inconclusive if only its CI reaches it.")
    # --- Fig. 8
    for w in (2, 3):
        names = {"MDRL-sparse": f"A3W{w}-sparse", "MEDC (6 experts)": f"A3W{w}-medc-six",
                 "RS (BFS shaping)": f"A3W{w}-rs", "IL-assisted RL (6 experts)": f"A3W{w}-il-six"}
        data = r.figure(f"fig8_A3W{w}.png", f"Fig. 8: A3W{w}, MEDC vs benchmarks", names)
        frl_csv = "metrics.csv" if w == 2 else "metrics_A3W3.csv"
        frl = r.series({"FRL (8 users, FedAvg)": "A3W2-frl8"}, frl_csv)
        if frl:
            data.update(frl)
            from ..plots import plot_methods

            plot_methods({k: (v[0], v[1]) for k, v in data.items()}, out / f"fig8_A3W{w}.png",
                         f"Fig. 8: A3W{w}, MEDC vs benchmarks")
        if data:
            frl_key = "A3W2-frl8" if w == 2 else "A3W2-frl8:metrics_A3W3.csv"
            r.add(f"### Fig. 8 — benchmarks (A3W{w})\n\n![fig8 A3W{w}](fig8_A3W{w}.png)\n\n"
                  + r.table(data, wall=True) + "\n\n" + "\n".join([
                r.gate(f"A3W{w}-sparse"),
                      r.claim(f"A3W{w}: MEDC beats FRL", f"A3W{w}-medc-six", frl_key, gate=f"A3W{w}-sparse"),
                      r.claim(f"A3W{w}: MEDC beats IL-assisted RL", f"A3W{w}-medc-six", f"A3W{w}-il-six",
                          gate=f"A3W{w}-sparse"),
                      r.claim(f"A3W{w}: MEDC matches or beats RS (paper: slight outperformance)",
                              f"A3W{w}-medc-six", f"A3W{w}-rs", gate=f"A3W{w}-sparse"),
                  ]) + "\n\nFRL wall time is for all 8 users together (they train in one process).")
    # RS wall-time overhead
    rs_ratio = []
    for w in (2, 3):
        _, _, s_sparse = load_curves(out, f"A3W{w}-sparse")
        _, _, s_rs = load_curves(out, f"A3W{w}-rs")
        if s_sparse and s_rs:
            rs_ratio.append((sum(s["train_seconds"] for s in s_rs) / len(s_rs))
                            / (sum(s["train_seconds"] for s in s_sparse) / len(s_sparse)))
    if rs_ratio:
        r.add("### RS wall-time overhead\n\n- **The paper: RS needed double the wall time of sparse** — "
              f"here RS / sparse training wall time = {', '.join(f'{x:.2f}' for x in rs_ratio)} (A3W2, A3W3; "
              "measured in the same worker pool, so it is noisy on a shared machine; `medc-bench train` "
              "gives a cleaner figure). The BFS distance field is computed once per episode on reset, so "
              "shaping costs little: the paper's 2x is not expected here, by design.")
    # --- Fig. 9
    data = r.figure("fig9.png", "Fig. 9: A3W2, 3 faulty of 8 users", {
        "MDRL-sparse": "A3W2-sparse", "MEDC (3 of 6 experts faulty)": "A3W2-medc-six-3faulty",
        "FRL (3 of 8 users faulty)": "A3W2-frl8-3faulty",
        "IL (3 of 6 experts faulty)": "A3W2-il-six-3faulty"})
    if data:
        r.add("### Fig. 9 — 3 faulty users out of 8 (A3W2)\n\n![fig9](fig9.png)\n\n" + r.table(data) + "\n\n"
              + "\n".join([
                r.gate("A3W2-sparse"),
                  r.claim("MEDC beats FRL with faulty users", "A3W2-medc-six-3faulty", "A3W2-frl8-3faulty",
                      gate="A3W2-sparse"),
                  r.claim("MEDC beats IL with faulty experts", "A3W2-medc-six-3faulty",
                          "A3W2-il-six-3faulty", gate="A3W2-sparse"),
              ]) + "\n\nFaulty users: A2W1 random, A2W2 biased (always action 0), A3W1 malicious (opposite "
              "of its own model's best move). In FRL they share poisoned parameters (random init / policy "
              "head forced to one action / negated policy head, see medc_training.frl).")
    # --- Figs. 10-11
    for short, app in ((spec["short"], spec["title"]) for spec in OTHER_APPS.values()):
        for fig, tag, what in (("10", "", "truthful experts"), ("11", "-3faulty", "3 faulty experts/users")):
            frl = f"{short}-frl7{tag}"
            data = r.figure(f"fig{fig}_{short}.png", f"Fig. {fig}: {app}, {what}", {
                "MDRL-sparse": f"{short}-sparse", "MEDC (6 experts)": f"{short}-medc{tag}",
                "FRL (7 users)": frl, "IL (6 experts)": f"{short}-il{tag}"},
                ylabel="mean episode length (sampled eval)")
            if data:
                r.add(f"### Fig. {fig} — {app}, {what}\n\n![fig{fig} {short}](fig{fig}_{short}.png)\n\n"
                      + r.table(data) + "\n\n" + "\n".join([
                r.gate(f"{short}-sparse"),
                          r.claim(f"{app} ({what}): MEDC beats FRL", f"{short}-medc{tag}", frl,
                              gate=f"{short}-sparse"),
                          r.claim(f"{app} ({what}): MEDC beats IL", f"{short}-medc{tag}", f"{short}-il{tag}",
                              gate=f"{short}-sparse"),
                      ]))
    # --- Supplement: longer runs (every step count found on disk)
    for tag in long_tags_on_disk(out / "runs", "A3W2-sparse"):
        steps_text = tag[4:]
        data = r.figure(f"{tag}_A3W2.png", f"Supplement: A3W2, {steps_text} steps", {
            "MDRL-sparse": f"{tag}-A3W2-sparse", "MEDC (6 experts)": f"{tag}-A3W2-medc-six",
            "MEDC (scripted oracle expert)": f"{tag}-A3W2-medc-oracle"})
        if data:
            r.add(f"### Supplement — longer runs (A3W2, {steps_text} steps)\n\n"
                  f"![{tag}]({tag}_A3W2.png)\n\n" + r.table(data) + "\n\n" + "\n".join([
                r.gate(f"{tag}-A3W2-sparse"),
                      r.claim(f"MEDC (6 trained experts) beats MDRL-sparse over {steps_text} steps",
                              f"{tag}-A3W2-medc-six", f"{tag}-A3W2-sparse", gate=f"{tag}-A3W2-sparse"),
                      r.claim(f"MEDC with a perfect (oracle) expert beats MDRL-sparse over {steps_text} "
                              "steps",
                              f"{tag}-A3W2-medc-oracle", f"{tag}-A3W2-sparse", gate=f"{tag}-A3W2-sparse"),
                  ]) + "\n\nThe oracle expert sees the target (BFS distance after each move); it is not "
                  "something a user could share, and is run only to separate 'MEDC does not help' from "
                  "'our experts are too weak to help'.")
    for tag in long_tags_on_disk(out / "runs", "maze-sparse"):
        steps_text = tag[4:]
        for short, app in ((spec["short"], spec["title"]) for spec in OTHER_APPS.values()):
            data = r.figure(f"{tag}_{short}.png", f"Supplement: {app}, {steps_text} steps", {
                "MDRL-sparse": f"{tag}-{short}-sparse", "MEDC (6 experts)": f"{tag}-{short}-medc",
                "IL (6 experts)": f"{tag}-{short}-il", "MEDC (3 of 6 faulty)": f"{tag}-{short}-medc-3faulty",
                "IL (3 of 6 faulty)": f"{tag}-{short}-il-3faulty"},
                ylabel="mean episode length (sampled eval)")
            if data:
                r.add(f"### Supplement — longer runs ({app}, {steps_text} steps)\n\n"
                      f"![{tag} {short}]({tag}_{short}.png)\n\n" + r.table(data) + "\n\n" + "\n".join([
                r.gate(f"{tag}-{short}-sparse"),
                          r.claim(f"{app}: MEDC beats MDRL-sparse over {steps_text} steps",
                                  f"{tag}-{short}-medc", f"{tag}-{short}-sparse",
                                      gate=f"{tag}-{short}-sparse"),
                          r.claim(f"{app}: MEDC beats IL over {steps_text} steps",
                                  f"{tag}-{short}-medc", f"{tag}-{short}-il", gate=f"{tag}-{short}-sparse"),
                          r.claim(f"{app}: MEDC with 3 faulty experts beats MDRL-sparse over {steps_text} "
                                  "steps", f"{tag}-{short}-medc-3faulty", f"{tag}-{short}-sparse",
                                      gate=f"{tag}-{short}-sparse"),
                          r.claim(f"{app}: MEDC beats IL, both with 3 faulty experts, over {steps_text} "
                                  "steps", f"{tag}-{short}-medc-3faulty", f"{tag}-{short}-il-3faulty",
                                      gate=f"{tag}-{short}-sparse"),
                      ]))
    scale_rows = "\n".join(f"| {k} | {v} |" for k, v in SCALES[scale].items())
    timing = ", ".join(f"{k} {v / 60:.1f} min" for k, v in elapsed.items())
    header = f"""# Reproduction report — scale `{scale}`

Made by:

```
{command}
```

Seeds: {seeds} per configuration (0..{seeds - 1}); curves are means over seeds with 95% CI bands
(Student t). Wall time of the phases run by this invocation:
{timing or 'none (report rebuilt from existing runs)'}.

**Metric.** As the paper: every `eval_every` training steps, `eval_steps` greedy test steps; the
mean length of the finished test episodes (max {plan.base['max_steps']} when the target is never found)
is plotted. Fleet coordination and maze cleaning (Figs. 10–11) run on the paper's {OTHER_GRID}×{OTHER_GRID}
grid with a {OTHER_MAX_STEPS}-step limit and are tested on actions sampled from the policy
({OTHER_EVAL['eval_envs']} environments × {OTHER_MAX_STEPS} steps per evaluation): a memoryless greedy policy
repeats one move forever in a coverage task.
Each claim compares *learning scores*: the mean evaluation episode length over the whole run
(the area under the learning curve divided by its length; lower = faster and better learning),
per seed, as a difference of means with a 95% CI (Welch standard error, Student t). "held" /
"contradicted" mean the CI of the difference excludes 0 in / against the paper's direction;
"not resolved" means the CI includes 0 (the note says which way the means lean); "no
difference" means identical scores (e.g. every episode hit the step limit).

**Scale.** Training steps per run: {budget['steps']:,} (fleet/maze {budget['fleet_maze_steps']:,}); experts
{budget['expert_steps']:,}; shipped team {budget['team_steps']:,}. Hyperparameters that differ from the
paper's table at this scale (everything else is the paper's: lr 3e-4, clip 0.2, entropy 0.01,
γ 0.99, λ 0.95, R_E 0.1, Q 0.05, R_S = QoS_i/ΣQoS_j):

| setting | value |
|---|---|
{scale_rows}

**Experts.** The expert bundles in `models/experts/` (and the shipped team) were trained by
this code: DAgger cloning of the scripted oracle in their own environment (`medc-clone`, see
`medc_training.dagger`), the cheapest way to get competent experts on 2 CPU cores; the paper's
experts were PPO-trained at full scale. The oracle sees the target; the clones see only the
agents' observations. Two architectures are mixed among the target-localization experts
(`lenet5` and `convnet-small`; MEDC needs only their actions, so one run uses both). Each
bundle's own evaluation (128 finished episodes, greedy and sampled, against a random team on
the same episodes; target localization is judged greedy, fleet and maze sampled):

{expert_table(plan.models) or "(no expert bundles found)"}

R_S of each expert follows the Models Manager contract's QoS rule (`medc_training.qos`) with
equal reputations (0.5): D_m is the mean |ΔE_i| over the environment attributes the expert and
the run both name (agents, walls, grid, step limit; the last two differ by 0 here), no expert
matches a run exactly (D_m = 0), and one without attributes (random, biased) counts as one unit
off in one of them.

"""
    protocol = out / "protocol.md"
    if protocol.exists():  # fixed before the runs it governs; see its first line
        header += "## Protocol\n\n" + protocol.read_text().strip() + "\n\n"
    header += f"**Verdicts.** {r.verdict_counts()} (each listed under its figure below).\n\n"
    notes = out / "discussion.md"
    if notes.exists():  # hand-written interpretation, kept across regenerations of the report
        header += "## Discussion\n\n" + notes.read_text().strip() + "\n\n## Figures and claims\n\n"
    return r.write(header)


# ------------------------------------------------------------------------------- main ---
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="medc-reproduce", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--scale", choices=sorted(BUDGETS), default="cpu")
    p.add_argument("--seeds", type=int, default=4, help="seeds per target-localization run (default 4)")
    p.add_argument("--out", default="docs/reproduction")
    p.add_argument("--only", action="append", choices=(*PHASES, "report"),
                   help="phase(s) to run (repeatable; default all). 'report' only rebuilds report.md")
    p.add_argument("--models", default="models", help="where expert/team bundles live (default models/)")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    p.add_argument("--steps", type=int, help="override the training steps of each experiment run")
    p.add_argument("--expert-steps", type=int, help="override the training steps of each expert")
    p.add_argument("--team-steps", type=int, help="override the training steps of the shipped team")
    p.add_argument("--other-steps", type=int, help="override the training steps of fleet/maze runs")
    p.add_argument("--long-steps", type=int, help="training steps of the supplementary long runs")
    p.add_argument("--other-seeds", type=int, default=2, help="seeds for Figs. 10-11 (default 2)")
    p.add_argument("--retrain", action="store_true", help="retrain experts even if bundles exist")
    p.add_argument("--no-other-apps", action="store_true", help="skip fleet/maze experts and Figs. 10-11")
    p.add_argument("--device", default="cpu",
                   help="torch device of every run: cpu or cuda (with cuda, --jobs 1)")
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error("--seeds must be >= 1")
    out, models = Path(args.out), Path(args.models)
    out.mkdir(parents=True, exist_ok=True)
    phases = args.only or list(PHASES)
    budget = {"steps": args.steps, "expert_steps": args.expert_steps, "team_steps": args.team_steps,
              "fleet_maze_steps": args.other_steps, "long_steps": args.long_steps}
    try:
        plan = Plan(args.scale, args.seeds, out, models, budget, args.other_seeds, device=args.device)
    except ValueError as exc:
        p.error(str(exc))
    command = "medc-reproduce " + " ".join(argv if argv is not None else sys.argv[1:])
    record = out / "command.txt"
    if phases != ["report"]:
        # The first full command plus any later ones that added runs (e.g. longer supplements).
        lines = record.read_text().splitlines() if record.exists() else []
        if command not in lines:
            record.write_text("\n".join([*lines, command]) + "\n")
    elif record.exists():  # a rebuilt report names the command that made its runs
        command = record.read_text().strip() + f"\n# report rebuilt with: {command}"
    elapsed: dict[str, float] = {}

    def timed(name, jobs):
        t0 = time.time()
        run_jobs(jobs, args.jobs, name)
        elapsed[name] = time.time() - t0

    if "experts" in phases:
        jobs = plan.expert_jobs(args.retrain)
        if not args.no_other_apps:
            jobs += plan.other_expert_jobs(args.retrain)
        timed("experts", jobs)
    tl_jobs: list[dict] = []
    for fig in ("fig6", "fig7", "fig8", "fig9"):
        if fig in phases:
            tl_jobs += plan.tl(fig)
    if "fig10" in phases and not args.no_other_apps:
        tl_jobs += plan.other_apps()
    if "long" in phases:
        tl_jobs += plan.long_runs()
    if "long-other" in phases and not args.no_other_apps:
        tl_jobs += plan.long_other_runs()
    if tl_jobs:
        unique = {j["out"]: j for j in tl_jobs}  # sparse baselines are shared by several figures
        # the longest jobs first so the pool's tail is short
        ordered = sorted(unique.values(), key=lambda j: -len(j["config"].get("frl_users") or [0]))
        timed("experiments", ordered)
    path = build_report(out, args.scale, args.seeds, command, plan, elapsed)
    print(f"report: {path}")
    print(json.dumps({"report": str(path), "elapsed_s": elapsed}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
