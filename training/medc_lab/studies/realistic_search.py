"""The realistic-search study: the learned team against the classical controllers on fixed episodes.

The protocol is fixed in docs/environments.md ("Realistic search: protocol"): the realistic sensing
preset, 3 agents, 100-step episodes, grids 20 and 30, walls 0, 2 and 5; random moves, the
classical controllers (:mod:`medc_training.controllers`) and MDRL-sparse (the CPU-scale default
learner, trained by ``scripts/realistic_runs.sh`` into ``<out>/runs/g{grid}w{walls}/seed{k}``)
each play the same 512 seeded episodes per scenario to their end
(:func:`medc_training.evaluate.play_episodes`).

``python -m medc_lab.cli.realistic evaluate --out docs/reproduction/realistic``
plays what is missing (one JSON of per-episode results per scenario and policy under
``<out>/eval``; finished ones are skipped, so the command resumes), and ``report`` writes the table
with 95% CIs and the protocol's verdicts (``<out>/table.md``, ``<out>/table.json``) and one figure
of learning curves with the controllers as reference lines (``<out>/curves.png``).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from medc_training.stats import mean_ci

#: The protocol's fixed values.
GRIDS = (20, 30)
WALLS = (0, 2, 5)
AGENTS = 3
MAX_STEPS = 100
EPISODES = 512
EVAL_SEED = 20261202
SEEDS = (0, 1, 2)
CLASSICAL = ("gradient", "greedy", "infotaxis")
BASELINES = ("random", *CLASSICAL)
#: Searchers played on the same episodes for the paired comparison
#: (:mod:`medc_lab.studies.realistic_searchers`), outside the protocol's table: the
#: information-driven controllers and the benchmark-trained team's bundles (repository paths).
SEARCHERS = ("infotaxis-exact", "space-aware")
TEAM_BUNDLES = {f"team-post-ft-s{k}": f"docs/reproduction/learned-team/main-posterior-ft/medc-s{k}/"
                                       "policy.safetensors" for k in SEEDS}
EXTRA = (*SEARCHERS, *TEAM_BUNDLES)
#: The repository root (TEAM_BUNDLES' relative paths start there).
ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class Scenario:
    grid: int
    walls: int

    @property
    def name(self) -> str:
        return f"g{self.grid}w{self.walls}"

    def make_env(self, policy: str, observation: str = "maps"):
        """The 512 environments the fixed episodes are played in (one round). The episodes do not
        depend on the observation (it draws nothing), so a policy that reads no observation gets
        the cheap 'maps' one and a bundle its own; the controllers get the team's posterior kept."""
        from medc_training.envs import make_batched
        from medc_training.envs.names import TARGET_LOCALIZATION

        return make_batched(TARGET_LOCALIZATION, num_envs=EPISODES, seed=EVAL_SEED, agents=AGENTS,
                            walls=self.walls, grid=self.grid, max_steps=MAX_STEPS, sensing="realistic",
                            posterior=policy in CLASSICAL or policy in SEARCHERS, copy_obs=False,
                            observation=observation)


SCENARIOS = tuple(Scenario(g, w) for g in GRIDS for w in WALLS)


def _bundle_path(name: str, out: Path, scenario: Scenario) -> Path:
    """'learned-seed{k}': the study's run; 'probe-{name}': ``<out>/probes/{name}/seed0``; a
    TEAM_BUNDLES name: its bundle in the repository."""
    if name in TEAM_BUNDLES:
        return ROOT / TEAM_BUNDLES[name]
    if name.startswith("probe-"):
        return out / "probes" / name.removeprefix("probe-") / "seed0" / "policy.safetensors"
    return out / "runs" / scenario.name / f"seed{name.removeprefix('learned-seed')}" / "policy.safetensors"


def _play(name: str, out: Path, scenario: Scenario):
    """Play policy ``name`` ('random', a controller, 'learned-seed{k}', 'probe-{name}' or an EXTRA
    name) on the scenario's fixed episodes. A bundle trained under another sensing preset than
    the study's is refused (BundleError)."""
    from medc_training.evaluate import net_policy, play_episodes

    if name == "random" or name in CLASSICAL or name in SEARCHERS:
        env = scenario.make_env(name)
        if name == "random":
            policy, greedy = None, False
        else:
            from medc_training.controllers import controller_policy

            policy, greedy = controller_policy(name, env), True
    else:
        from medc_training.bundle import check_sensing, load_bundle, manifest_observation

        bundle = load_bundle(_bundle_path(name, out, scenario))
        check_sensing(bundle.manifest, "realistic", name)
        env = scenario.make_env(name, manifest_observation(bundle.manifest))
        policy, greedy = net_policy(bundle.net), True
    return play_episodes(env, policy, episodes=EPISODES, seed=EVAL_SEED, greedy=greedy)


def evaluate(out: Path, policies: list[str] | None = None, scenarios: list[str] | None = None,
             probes: list[str] | None = None, extra: list[str] | None = None) -> list[Path]:
    """Play every missing (scenario, policy) evaluation, each named probe on the scenarios given
    and each EXTRA name in ``extra`` on every scenario selected; returns the files written.
    With ``extra`` given, ``policies`` selects among the protocol's policies only when named."""
    written = []
    for sc in SCENARIOS:
        if scenarios and sc.name not in scenarios:
            continue
        names = list(BASELINES) + [f"learned-seed{k}" for k in SEEDS
                                   if (out / "runs" / sc.name / f"seed{k}" / "summary.json").exists()]
        names = [n for n in names if (not policies and not extra) or n in (policies or ())
                 or n.split("-")[0] in (policies or ())]
        names += [f"probe-{p}" for p in probes or () if scenarios]
        names += [n for n in EXTRA if n in (extra or ())]
        for name in names:
            path = out / "eval" / sc.name / f"{name}.json"
            if path.exists():
                continue
            print(f"[search-study] {sc.name} {name} ...", file=sys.stderr, flush=True)
            start = time.perf_counter()
            result = _play(name, out, sc)
            seconds = round(time.perf_counter() - start, 1)
            print(f"[search-study] {sc.name} {name}: {seconds} s", file=sys.stderr, flush=True)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"scenario": sc.name, "policy": name, "episodes": EPISODES,
                                        "seed": EVAL_SEED, "lengths": list(result.lengths),
                                        "successes": [bool(s) for s in result.successes],
                                        "seconds": seconds}))
            written.append(path)
    return written


def _load(out: Path, sc: Scenario, name: str) -> dict | None:
    path = out / "eval" / sc.name / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _disjoint(a: tuple[float, float], b: tuple[float, float]) -> int:
    """-1 when mean a is below b with disjoint CIs, +1 above, 0 when they overlap."""
    (ma, ha), (mb, hb) = a, b
    if ma + ha < mb - hb:
        return -1
    if ma - ha > mb + hb:
        return 1
    return 0


def summarize(out: Path) -> list[dict]:
    """One row per scenario: each policy's mean length and success rate with 95% CIs, and the
    protocol's gate and verdict."""
    rows = []
    for sc in SCENARIOS:
        row: dict = {"scenario": sc.name, "grid": sc.grid, "walls": sc.walls, "policies": {}}
        for name in BASELINES:
            data = _load(out, sc, name)
            if data is not None:
                row["policies"][name] = {
                    "length": mean_ci([float(v) for v in data["lengths"]]),
                    "success": mean_ci([float(v) for v in data["successes"]]),
                }
        learned = [d for k in SEEDS if (d := _load(out, sc, f"learned-seed{k}")) is not None]
        if learned:
            lengths = [sum(d["lengths"]) / len(d["lengths"]) for d in learned]
            success = [sum(d["successes"]) / len(d["successes"]) for d in learned]
            row["policies"]["learned"] = {"length": mean_ci(lengths), "success": mean_ci(success),
                                          "seeds": len(learned)}
        row.update(_verdict(row["policies"]))
        rows.append(row)
    return rows


def _verdict(policies: dict) -> dict:
    learned, rnd = policies.get("learned"), policies.get("random")
    classical = {k: v for k, v in policies.items() if k in CLASSICAL}
    missing = len(classical) < len(CLASSICAL) or (learned or {}).get("seeds", 0) < len(SEEDS)
    if learned is None or rnd is None or missing:
        return {"gate": "not run", "verdict": "not run"}
    if _disjoint(learned["length"], rnd["length"]) != -1:
        return {"gate": "fails", "verdict": "not testable"}
    best = min(classical, key=lambda k: classical[k]["length"][0])
    side = _disjoint(learned["length"], classical[best]["length"])
    verdict = {-1: "yes", 1: "no", 0: "not resolved"}[side]
    return {"gate": "passes", "best_classical": best, "verdict": verdict}


def _cell(stat: tuple[float, float], scale: float = 1.0, digits: int = 1) -> str:
    mean, half = stat
    if math.isnan(mean):
        return "–"
    return f"{mean * scale:.{digits}f} ± {half * scale:.{digits}f}"


def table_markdown(rows: list[dict]) -> str:
    """The study's table: mean episode length (steps) and success rate (%) with 95% CIs."""
    cols = ["random", *CLASSICAL, "learned"]
    head = "| scenario | " + " | ".join(cols) + " | gate | learned beats best classical |"
    lines = [head, "|" + " --- |" * (len(cols) + 3)]
    for row in rows:
        cells = []
        for name in cols:
            p = row["policies"].get(name)
            cells.append("not run" if p is None else
                         f"{_cell(p['length'])} steps, {_cell(p['success'], 100.0, 0)}%")
        best = f" ({row['best_classical']})" if row.get("best_classical") else ""
        grid = f"{row['grid']}×{row['grid']}, {row['walls']} walls"
        lines.append(f"| {grid} | " + " | ".join(cells) + f" | {row['gate']} | {row['verdict']}{best} |")
    return "\n".join(lines) + "\n"


def figure(out: Path, rows: list[dict], png: Path) -> None:
    """Learning curves of the learned runs (mean and 95% band over seeds of the fixed-episode
    evaluations in metrics.csv) with each baseline's fixed-episode mean as a horizontal line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from medc_training.metrics import read_metrics
    from medc_training.stats import curve_band

    fig, axes = plt.subplots(len(GRIDS), len(WALLS), figsize=(4.2 * len(WALLS), 3.4 * len(GRIDS)),
                             squeeze=False)
    colours = {"random": "grey", "gradient": "tab:orange", "greedy": "tab:green", "infotaxis": "tab:purple"}
    for ax, row in zip(axes.flat, rows):
        curves, steps = [], None
        for k in SEEDS:
            path = out / "runs" / row["scenario"] / f"seed{k}" / "metrics.csv"
            if path.exists():
                data = read_metrics(path)
                steps = [r["step"] for r in data]
                curves.append([r["episode_length"] for r in data])
        if curves:
            n = min(len(c) for c in curves)
            mean, half = curve_band([c[:n] for c in curves])
            x = np.asarray(steps[:n])
            ax.plot(x, mean, color="tab:blue", label=f"MDRL-sparse ({len(curves)} seeds)")
            ax.fill_between(x, mean - half, mean + half, color="tab:blue", alpha=0.2)
        for name, colour in colours.items():
            p = row["policies"].get(name)
            if p is not None:
                ax.axhline(p["length"][0], color=colour, linestyle="--", label=name)
        ax.set_title(f"{row['grid']}×{row['grid']}, {row['walls']} walls")
        ax.set_xlabel("training steps")
        ax.set_ylabel("mean episode length (fixed episodes)")
        ax.set_ylim(0, MAX_STEPS + 2)
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def report(out: Path) -> dict:
    """Write table.md, table.json and curves.png under ``out``; returns the JSON summary."""
    rows = summarize(out)
    (out / "table.md").write_text(table_markdown(rows))
    (out / "table.json").write_text(json.dumps(rows, indent=1))
    figure(out, rows, out / "curves.png")
    return {"scenarios": len(rows), "verdicts": {r["scenario"]: r["verdict"] for r in rows}}
