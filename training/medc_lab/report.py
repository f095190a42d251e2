"""The report: report.md and its figures, built from whatever runs exist under OUT/runs/.

Every section is generated from the figure declarations (:mod:`.figures`); every band, table
and verdict uses :mod:`medc_training.stats`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Collection, Sequence
from pathlib import Path

from medc_training.stats import compare, learning_score, mean_ci

from .catalogue import OTHER_EVAL, OTHER_GRID, OTHER_MAX_STEPS, Scope, long_tags_on_disk, tl_architectures
from .figures import FIGURES, TAGGED, Figure, Panel, tag_markers
from .plan import Plan
from .posthoc import posthoc_section
from .references import (
    CONTROLLERS,
    load_references,
    reference_text,
    regime_name,
    speed_section,
    versus_best,
    versus_reference,
)


def seed_dirs(out: Path, name: str, seeds: Collection[int] | None = None) -> list[Path]:
    """The finished seeds' folders of one run name (``runs/<name>/seed<k>/`` holding its
    summary.json), in order; ``seeds``: only those seeds (None: all)."""
    wanted = None if seeds is None else {f"seed{k}" for k in seeds}
    return [d for d in sorted((out / "runs" / name).glob("seed*"))
            if (d / "summary.json").exists() and (wanted is None or d.name in wanted)]


def load_curves(out: Path, name: str, csv_name: str = "metrics.csv", seeds: Collection[int] | None = None
                ) -> tuple[list[float], list[list[float]], list]:
    """(steps, [episode-length curve per seed], [summary per seed]) of one run name (``seeds``:
    only those seeds)."""
    from medc_training.metrics import read_metrics

    curves, summaries, steps = [], [], []
    for seed_dir in seed_dirs(out, name, seeds):
        if not (seed_dir / csv_name).exists():
            continue
        rows = read_metrics(seed_dir / csv_name)
        if len(rows) > len(steps):
            steps = [r["step"] for r in rows]
        curves.append([r["episode_length"] for r in rows])
        summaries.append(json.loads((seed_dir / "summary.json").read_text()))
    return steps, curves, summaries


#: Seeds the learnability gate needs before it can pass.
GATE_MIN_SEEDS = 3
#: Random play's episodes per seed for the gate under the legacy window evaluator (the first to
#: finish); under fixed episodes random play plays the run's own evaluation episodes.
GATE_RANDOM_EPISODES = 256


def _episodes_key(cfg: dict, episodes: int | None) -> str:
    """The key of a run's evaluation episodes (or of ``episodes`` fixed episodes of its evaluation
    seed) in OUT/random_play.json and OUT/controller_play.json."""
    from medc_training.config import TrainConfig
    from medc_training.ppo import EVAL_SEED_OFFSET

    c = TrainConfig.from_dict(cfg)
    key = (f"{c.env}|agents={c.agents}|walls={c.walls}|grid={c.grid}|max_steps={c.max_steps}|"
           f"{json.dumps(c.env_options, sort_keys=True)}|seed={c.seed + EVAL_SEED_OFFSET}")
    fixed = episodes or c.eval_episodes
    return key + (f"|episodes={fixed}|envs={c.eval_envs}" if fixed else "")


def random_play(out: Path, cfg: dict, episodes: int | None = None) -> dict:
    """{"episode_length", "success_rate"} of uniformly random valid moves on a run's evaluation
    episodes (its evaluation seed and environment), cached in OUT/random_play.json.

    With fixed-episode evaluation these are exactly the run's ``eval_episodes`` episodes, each
    played to its end (:func:`medc_training.evaluate.play_episodes`); a run evaluated with the
    legacy window (``eval_episodes`` 0) gets the legacy baseline it was gated with: the first
    GATE_RANDOM_EPISODES episodes to finish (:func:`medc_training.evaluate.play`). ``episodes``:
    that many fixed episodes of the run's evaluation seed instead of its own evaluation's. A cache
    entry written before success rates were kept holds the mean length alone: asked for both, the
    same episodes are played again (random play is seeded) and the entry holds both from then on."""
    from medc_training.config import TrainConfig
    from medc_training.evaluate import play, play_episodes
    from medc_training.ppo import EVAL_SEED_OFFSET, make_env_for

    key = _episodes_key(cfg, episodes)
    cache_path = out / "random_play.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if not isinstance(cache.get(key), dict):
        c = TrainConfig.from_dict(cfg)
        seed = c.seed + EVAL_SEED_OFFSET
        env = make_env_for(c, c.eval_envs, seed, False)
        fixed = episodes or c.eval_episodes
        if fixed:
            played = play_episodes(env, None, episodes=fixed, greedy=False, seed=seed)
        else:
            played = play(env, None, episodes=GATE_RANDOM_EPISODES, greedy=False, seed=seed)
        summary = played.summary()
        cache[key] = {"episode_length": summary["episode_length"], "success_rate": summary["success_rate"]}
        cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return cache[key]


def random_play_length(out: Path, cfg: dict, episodes: int | None = None) -> float:
    """The mean episode length of :func:`random_play` (an entry cached with the length alone is
    read as it is: nothing is played again)."""
    cache_path = out / "random_play.json"
    cached = (json.loads(cache_path.read_text()) if cache_path.exists() else {}).get(
        _episodes_key(cfg, episodes))
    if isinstance(cached, int | float):
        return float(cached)
    return float(random_play(out, cfg, episodes)["episode_length"])


#: The classical controllers' play on runs' evaluation episodes (:func:`controller_play`).
CONTROLLER_PLAY = "controller_play.json"


def controller_env(c, seed: int):
    """The batched core of config ``c`` (a :class:`~medc_training.config.TrainConfig`) on which the
    classical controllers play its evaluation episodes: the run's own evaluation environment
    (:func:`medc_training.ppo.make_env_for`, ``eval_envs`` environments, seeded ``seed``) with the
    team's source posterior kept, which the controllers read and which changes no episode."""
    from medc_training.ppo import make_env_for

    return make_env_for(c, c.eval_envs, seed, False, posterior=True)


def eval_config(cfg: dict, csv_name: str = "metrics.csv") -> dict:
    """The config whose evaluation episodes a run's ``csv_name`` measured: the run's own for
    metrics.csv; for an FRL side user's metrics_<AyWz>.csv, the run's with that user's agents, walls
    and environment options (the user is evaluated on its own environment from the run's evaluation
    seed, :mod:`medc_training.frl`). Raises ValueError for a side user the run does not have."""
    if csv_name == "metrics.csv":
        return cfg
    name = csv_name.removeprefix("metrics_").removesuffix(".csv")
    for user in cfg.get("frl_users") or ():
        agents, walls = user.get("agents", cfg["agents"]), user.get("walls", cfg["walls"])
        if f"A{agents}W{walls}" == name:
            return {**cfg, "agents": agents, "walls": walls,
                    "env_options": user.get("env_options", cfg["env_options"])}
    raise ValueError(f"{csv_name}: the run has no FRL user {name!r}")


def _controllers_refuse(c) -> str | None:
    """Why the classical controllers cannot play the evaluation episodes of config ``c`` (a
    :class:`~medc_training.config.TrainConfig`); None when they can."""
    from medc_training.envs import application

    if not c.eval_episodes:
        return "a run evaluated with the legacy window has no fixed evaluation episodes"
    if not application(c.env).controllers:
        return f"the classical controllers read the team's source estimate; {c.env!r} keeps none"
    return None


def controller_play(out: Path, cfg: dict, controllers: Sequence[str] = CONTROLLERS) -> dict[str, dict]:
    """{controller: {"lengths", "successes"}} (per episode, in episode order) of each classical
    controller (:mod:`medc_training.controllers`, played greedily) on a run's evaluation episodes:
    its ``eval_episodes`` fixed episodes of its evaluation seed and environment
    (:func:`controller_env`), each played to its end, exactly as the run's evaluations played
    them (:func:`medc_training.evaluate.play_episodes`). Cached in OUT/controller_play.json by the
    episodes' key and controller; only what the cache lacks is played. Raises ValueError for a run
    evaluated with the legacy window (no fixed episodes) or of another application."""
    from medc_training.config import TrainConfig
    from medc_training.controllers import controller_policy
    from medc_training.evaluate import play_episodes
    from medc_training.ppo import EVAL_SEED_OFFSET

    c = TrainConfig.from_dict(cfg)
    refused = _controllers_refuse(c)
    if refused:
        raise ValueError(refused)
    key = _episodes_key(cfg, None)
    cache_path = out / CONTROLLER_PLAY
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    entry = cache.setdefault(key, {})
    seed = c.seed + EVAL_SEED_OFFSET
    env = None
    for name in controllers:
        if name in entry:
            continue
        env = env or controller_env(c, seed)
        played = play_episodes(env, controller_policy(name, env), episodes=c.eval_episodes, seed=seed)
        entry[name] = {"lengths": [int(x) for x in played.lengths],
                       "successes": [bool(x) for x in played.successes]}
        cache_path.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return {name: entry[name] for name in controllers}


def controller_lengths(out: Path, summaries: Sequence[dict], csv_name: str = "metrics.csv"
                       ) -> list[dict[str, float]] | None:
    """Per seed (``summaries``: one summary.json each), each classical controller's mean episode
    length on the evaluation episodes behind that seed's ``csv_name`` (:func:`controller_play`);
    None when a seed has no fixed evaluation episodes or its application keeps no source estimate."""
    from medc_training.config import TrainConfig

    lengths = []
    for summary in summaries:
        cfg = eval_config(summary["config"], csv_name)
        if _controllers_refuse(TrainConfig.from_dict(cfg)):
            return None
        played = controller_play(out, cfg)
        lengths.append({name: sum(p["lengths"]) / len(p["lengths"]) for name, p in played.items()})
    return lengths


def learnability_gate(out: Path, sparse_run: str, min_seeds: int = GATE_MIN_SEEDS,
                      random_episodes: int | None = None, seeds: Collection[int] | None = None) -> dict:
    """Did MDRL-sparse learn in ``sparse_run``'s environment? Per seed, its final evaluation episode
    length (mean of the last three evaluations) minus random play's on the same evaluation
    episodes (or on ``random_episodes`` fixed episodes of the same seed); passed when >= ``min_seeds``
    seeds ran and the 95% CI of the mean difference lies entirely below 0 (``seeds``: only those
    seeds count). Returns {"passed", "n", "sparse", "random", "diff", "half", "text"}."""
    from medc_training.metrics import read_metrics

    finals, randoms = [], []
    for seed_dir in seed_dirs(out, sparse_run, seeds):
        summary = json.loads((seed_dir / "summary.json").read_text())
        rows = read_metrics(seed_dir / "metrics.csv")
        finals.append(sum(r["episode_length"] for r in rows[-3:]) / len(rows[-3:]))
        randoms.append(random_play_length(out, summary["config"], random_episodes))
    diffs = [f - r for f, r in zip(finals, randoms)]
    m, half = mean_ci(diffs)
    passed = len(diffs) >= min_seeds and m + half < 0
    ms, _ = mean_ci(finals)
    mr, _ = mean_ci(randoms)
    where = (f"{random_episodes} fixed episodes of each seed" if random_episodes
             else "the same evaluation episodes")
    text = (f"MDRL-sparse final episode length {ms:.2f} vs random play {mr:.2f} on {where}: difference "
            f"{m:+.2f} ± {half:.2f} (95% CI, n = {len(diffs)} seeds)")
    return {"passed": passed, "n": len(diffs), "sparse": ms, "random": mr, "diff": m, "half": half,
            "text": text}


def verdict(better: list[float], worse: list[float], underpowered: float | None = None) -> str:
    """How the paper's claim "``better`` learns faster than ``worse``" fared (lower learning
    score is better): held / contradicted when the 95% CI of the difference excludes 0, else
    not resolved, saying which way the means lean (and "under-powered" when the CI's half-width
    exceeds ``underpowered``)."""
    if not better or not worse:
        return "not run"
    c = compare(better, worse)
    if c["diff"] == 0:
        return "no difference"
    if c["diff"] + c["half"] < 0:
        return "held"
    if c["diff"] - c["half"] > 0:
        return "contradicted (CI excludes 0 the other way)"
    weak = ", under-powered" if underpowered is not None and c["half"] > underpowered else ""
    if c["diff"] < 0:
        return f"not resolved (means lean the paper's way; CI includes 0{weak})"
    return f"not resolved (means lean against the paper; CI includes 0{weak})"


class Report:
    """Collects figures and claim verdicts into report.md."""

    def __init__(self, out: Path, scale: str, seeds: int, command: str, scope: Scope | None = None,
                 base: dict | None = None) -> None:
        self.out, self.scale, self.seeds, self.command = out, scale, seeds, command
        self.scope = scope or Scope()
        #: The scale's run configuration (grid and step limit name a panel's reference regime).
        self.base = base or {}
        self.sections: list[str] = []
        self.scores: dict[str, list[float]] = {}
        #: Learnability gate of each environment, by (its MDRL-sparse run name, the seeds it needs,
        #: the seeds it reads or None for all).
        self.gates: dict[tuple, dict] = {}
        #: The verdict word of every claim written, in order (for the counts).
        self.verdicts: list[str] = []
        #: Per series key, its learning score by seed (the seed its config names), as last read.
        self.seed_scores: dict[str, dict[int, float]] = {}
        #: Every claim written, in order, with what its analysis after the protocol needs
        #: (:mod:`.posthoc`): its text, the verdict word, the margin (None: "beats") and both sides'
        #: scores by seed as the claim read them.
        self.claim_records: list[dict] = []
        #: The panels with a steps-to-sparse's-level line: (heading, data, sparse's label).
        self.speeds: list[tuple[str, dict, str]] = []

    def figure_seeds(self, fig: Figure) -> tuple[int, ...] | None:
        """The seeds the report reads for ``fig``: those it plans when it reads only those
        (Figure.planned_seeds_only), else None (all that ran)."""
        if not fig.planned_seeds_only or fig.max_seeds is None:
            return None
        return tuple(range(self.scope.first_seed, self.scope.first_seed + fig.max_seeds))

    def gate_result(self, sparse_run: str, min_seeds: int | None = None,
                    seeds: tuple[int, ...] | None = None) -> dict:
        """:func:`learnability_gate` of ``sparse_run`` (needing ``min_seeds``, None: the scope's;
        reading ``seeds``, None: all), computed once per report."""
        need = min_seeds or self.scope.gate_min_seeds
        key = (sparse_run, need, seeds)
        if key not in self.gates:
            self.gates[key] = learnability_gate(self.out, sparse_run, need, self.scope.gate_random_episodes,
                                                seeds)
        return self.gates[key]

    def gate(self, sparse_run: str, min_seeds: int | None = None,
             seeds: tuple[int, ...] | None = None) -> str:
        """The gate line for ``sparse_run``'s environment; claims made with ``gate=sparse_run``
        are "not testable" unless it passed."""
        g = self.gate_result(sparse_run, min_seeds, seeds)
        if g["n"] == 0:
            return "- **Learnability gate** — not run"
        need = min_seeds or self.scope.gate_min_seeds
        if g["passed"]:
            word = "passed"
        elif g["n"] < need:
            word = (f"NOT passed yet (needs >= {need} seeds, {g['n']} ran): this environment's claims "
                    "are not testable until the rest of MDRL-sparse's seeds have run")
        else:
            word = (f"NOT passed (needs >= {need} seeds and a CI below 0): the scale is too small for "
                    "MDRL-sparse to learn here, so this environment's claims are not testable")
        return f"- **Learnability gate** ({sparse_run}) — {word}: {g['text']}"

    def _untestable(self, gate: str | None, min_seeds: int | None = None,
                    seeds: tuple[int, ...] | None = None) -> str | None:
        if gate is None:
            return None
        g = self.gate_result(gate, min_seeds, seeds)
        if g["passed"]:
            return None
        return (f"not testable (MDRL-sparse did not pass the learnability gate: difference to random "
                f"play {g['diff']:+.2f} ± {g['half']:.2f}, n = {g['n']})")

    def _incomplete(self, a: list, b: list) -> str | None:
        """"incomplete ..." when a side of a claim (its seeds' scores ``a``, ``b``) has fewer seeds
        than the scope's ``claim_min_seeds`` (but at least one: none is "not run")."""
        need = self.scope.claim_min_seeds
        if need is None or not a or not b or (len(a) >= need and len(b) >= need):
            return None
        return f"incomplete ({len(a)} and {len(b)} of {need} seeds ran; no verdict yet)"

    def series(self, names: dict[str, str], csv_name: str = "metrics.csv",
               seeds: tuple[int, ...] | None = None) -> dict:
        data = {}
        for label, name in names.items():
            steps, curves, summaries = load_curves(self.out, name, csv_name, seeds)
            if curves:
                data[label] = (steps, curves, summaries)
                key = name if csv_name == "metrics.csv" else f"{name}:{csv_name}"
                self.scores[key] = [learning_score(c) for c in curves]
                self.seed_scores[key] = {int(s["config"]["seed"]): score
                                         for s, score in zip(summaries, self.scores[key], strict=True)}
        return data

    def figure(self, png: str, title: str, names: dict[str, str], csv_name: str = "metrics.csv",
               ylabel: str = "mean episode length (greedy eval)") -> dict:
        from medc_training.plots import plot_methods

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

    def claim(self, text: str, better: str, worse: str, gate: str | None = None, *,
              min_seeds: int | None = None, seeds: tuple[int, ...] | None = None) -> str:
        """A claim's verdict line; "not testable" unless ``gate``'s learnability gate passed (with
        ``min_seeds`` and ``seeds`` as in :meth:`gate_result`)."""
        a, b = self.scores.get(better, []), self.scores.get(worse, [])
        c = compare(a, b) if a and b else {"diff": math.nan, "half": math.nan}
        blocked = self._untestable(gate, min_seeds, seeds) if a and b else None
        word = blocked or self._incomplete(a, b) or verdict(a, b, self.scope.underpowered)
        self.verdicts.append(word)
        self._record(text, word, better, worse, None)
        return (f"- **{text}** — {word}: difference of learning scores "
                f"{c['diff']:+.2f} ± {c['half']:.2f} (negative = first is better; n = {len(a)} vs {len(b)})")

    def claim_no_worse(self, text: str, faulty: str, sparse: str, margin: float,
                       gate: str | None = None, *, min_seeds: int | None = None,
                       seeds: tuple[int, ...] | None = None) -> str:
        a, b = self.scores.get(faulty, []), self.scores.get(sparse, [])
        if not a or not b:
            self.verdicts.append("not run")  # counted with the others, as claim() counts it
            return f"- **{text}** — not run"
        c = compare(a, b)
        ok = c["diff"] - c["half"] <= margin
        word = "held" if c["diff"] <= margin and ok else ("inconclusive" if ok else "did not hold")
        word = self._untestable(gate, min_seeds, seeds) or self._incomplete(a, b) or word
        self.verdicts.append(word)
        self._record(text, word, faulty, sparse, margin)
        return (f"- **{text}** — {word}: {c['diff']:+.2f} ± {c['half']:.2f} episode-length steps vs sparse "
                f"(allowed margin {margin:+.1f}; n = {len(a)} vs {len(b)})")

    def _record(self, text: str, word: str, first: str, second: str, margin: float | None) -> None:
        self.claim_records.append({"text": text, "word": word, "margin": margin,
                                   "first": dict(self.seed_scores.get(first, {})),
                                   "second": dict(self.seed_scores.get(second, {}))})

    def add(self, text: str) -> None:
        self.sections.append(text)

    def references(self, walls: int, grid: int | None = None) -> dict[str, dict]:
        """The reference lines (:mod:`.references`) of the regime with ``walls`` obstructions on
        the ``grid`` (None: the scale's), or {} when this scope has none or they were not played
        on that regime."""
        if self.scope.reference is None or "grid" not in self.base:
            return {}
        regime = regime_name(grid or self.base["grid"], walls, self.base["max_steps"])
        return load_references(self.out / self.scope.reference / regime)

    def summaries(self, name: str) -> list[dict]:
        """The summary.json of every finished seed of run ``name``."""
        return load_curves(self.out, name)[2]

    def seed_rows(self, name: str, seeds: tuple[int, ...] | None = None) -> list[tuple[dict, list[dict]]]:
        """(summary, metrics.csv rows) of every finished seed of run ``name`` (``seeds``: only those)."""
        from medc_training.metrics import read_metrics

        return [(json.loads((d / "summary.json").read_text()), read_metrics(d / "metrics.csv"))
                for d in seed_dirs(self.out, name, seeds) if (d / "metrics.csv").exists()]

    def random_success(self, sparse_run: str, seeds: tuple[int, ...] | None = None) -> float:
        """Random valid moves' success rate on the learnability gate's episodes of ``sparse_run``'s
        seeds (their mean; nan when none ran)."""
        rates = [random_play(self.out, summary["config"], self.scope.gate_random_episodes)["success_rate"]
                 for summary, _ in self.seed_rows(sparse_run, seeds)]
        return sum(rates) / len(rates) if rates else math.nan

    def verdict_counts(self) -> str:
        """One line counting the claims by verdict (held, contradicted, not resolved, ...)."""
        kinds = ("held", "contradicted", "did not hold", "inconclusive", "not resolved", "not testable",
                 "no difference", "incomplete", "not run")
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
    from medc_training.bundle import BundleError, read_manifest

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


def report_figures(runs: Path) -> list[Figure]:
    """The figures of the report: every phase's, the tagged supplements once per step count that
    ran; a figure that borrows runs of others (the sweep) once a run of its own has finished."""
    figures = []
    for phase, make in FIGURES.items():
        if phase in TAGGED:
            figures += [make(tag) for tag in long_tags_on_disk(runs, tag_markers(phase))]
            continue
        fig = make()
        own = [run.name for run in fig.runs() if run.name not in fig.borrowed]
        if not fig.borrowed or any(seed_dirs(runs.parent, name) for name in own):
            figures.append(fig)
    return figures


def panel_section(r: Report, panel: Panel, seeds: tuple[int, ...] | None = None,
                  gate_min_seeds: int | None = None) -> str | None:
    """A panel's plot and section (its table, gate and claims), or None when none of its runs exist
    (``seeds``: only those seeds are read; ``gate_min_seeds``: the gate's need, None: the scope's)."""
    from medc_training.plots import plot_methods

    data: dict = {}
    for s in panel.series:
        data.update(r.series({s.label: s.run.name}, s.csv, seeds))
    if not data:
        return None
    refs = r.references(panel.gate.walls, panel.grid)
    plot_methods({k: (v[0], v[1]) for k, v in data.items()}, r.out / panel.png, panel.title, panel.ylabel,
                 references={k: (v["length"], v["length_ci"]) for k, v in refs.items()} or None)
    table = r.table(data, wall=panel.wall)
    lines = [r.gate(panel.gate.name, gate_min_seeds, seeds)]
    if refs:
        lines.append(reference_text(refs))
        finals = [versus_reference(label, v[1], refs) for label, v in data.items()]
        lines.append("- **Final policies against the best classical controller** (as the protocol fixed "
                     "it: difference of mean episode lengths, the controller's on the reference episodes, "
                     "95% CI): " + "; ".join(f for f in finals if f))
        csvs = {s.label: s.csv for s in panel.series}
        paired = [versus_best(label, v[1], controller_lengths(r.out, v[2], csvs[label]))
                  for label, v in data.items()]
        if any(paired):
            lines.append("- **The same on each seed's own evaluation episodes** (added after the protocol: "
                         "per seed, the final level minus the controller's mean episode length on the "
                         "same episodes; the mean of these differences over the seeds with a 95% CI, "
                         "Student t; against the controller with the lowest mean length on those "
                         "episodes): " + "; ".join(f for f in paired if f))
        sparse_label = next(s.label for s in panel.series if s.run == panel.gate)
        speed = speed_section(data, sparse_label)
        if speed:
            lines.append(speed)
            if panel.claims:
                r.speeds.append((panel.heading.lstrip("# "), data, sparse_label))
    rules = {"min_seeds": gate_min_seeds, "seeds": seeds}
    for c in panel.claims:
        if c.margin is None:
            lines.append(r.claim(c.text, c.better.key, c.worse.key, gate=panel.gate.name, **rules))
        else:
            lines.append(r.claim_no_worse(c.text, c.better.key, c.worse.key, c.margin, gate=panel.gate.name,
                                          **rules))
    text = f"{panel.heading}\n\n![{panel.alt}]({panel.png})\n\n{table}\n\n" + "\n".join(lines)
    return text + (f"\n\n{panel.note}" if panel.note else "")


#: How a report's curves were measured, by evaluator (:func:`metric_text`).
WINDOW_METRIC = """\
**Metric.** As the paper: every `eval_every` training steps, `eval_steps` greedy test steps; the
mean length of the finished test episodes (max {max_steps} when the target is never found)
is plotted. Fleet coordination and maze cleaning (Figs. 10–11) run on the paper's {grid}×{grid}
grid with a {limit}-step limit and are tested on actions sampled from the policy
({envs} environments × {limit} steps per evaluation): a memoryless greedy policy
repeats one move forever in a coverage task."""
EPISODES_METRIC = """\
**Metric.** Every `eval_every` training steps, {episodes} fixed greedy test episodes (the same for
every evaluation, and for every method's run of a seed), each played to its end; their mean length
(an episode that never finds the target counts {max_steps}) is plotted. Fleet coordination and maze
cleaning (Figs. 10–11) run on the paper's {grid}×{grid} grid with a {limit}-step limit and are tested on
actions sampled from the policy ({other} fixed episodes per evaluation): a memoryless greedy policy
repeats one move forever in a coverage task."""


def metric_text(plan: Plan) -> str:
    """The report's paragraph on how its curves were measured: the legacy window (a plan whose
    folder holds window-evaluated runs) or fixed episodes."""
    values = {"max_steps": plan.base["max_steps"], "grid": OTHER_GRID, "limit": OTHER_MAX_STEPS}
    if plan.window_eval:
        return WINDOW_METRIC.format(envs=OTHER_EVAL["eval_envs"], **values)
    return EPISODES_METRIC.format(episodes=plan.base["eval_episodes"], other=OTHER_EVAL["eval_episodes"],
                                  **values)


def expert_quality(r: Report, plan: Plan) -> str:
    """With reference lines (the claims protocol): the experts played on the reference lines' fixed
    episodes, on their own environment and as the team, beside the controllers; else nothing."""
    from .expert_eval import EPISODES, evaluate_experts, expert_eval_table

    if plan.scope.reference is None:
        return ""
    table = expert_eval_table(evaluate_experts(r.out, plan.models, plan.base), r.references(2))
    if not table:
        return ""
    return (f"\nThe same experts played greedily on the reference lines' {EPISODES} fixed episodes, on their "
            "own environment and as the A3W2 team the runs train, beside random moves and the classical "
            f"controllers on the team's episodes:\n\n{table}\n")


def build_report(out: Path, scale: str, seeds: int, command: str, plan: Plan, elapsed: dict) -> Path:
    from medc_training.config import SCALES

    r = Report(out, scale, seeds, command, plan.scope, plan.base)
    first = plan.scope.first_seed
    budget = plan.budget
    for fig in report_figures(out / "runs"):
        for panel in fig.panels:
            if not plan.planned(panel.gate):
                continue  # a panel of a team this scope does not train (e.g. an FRL side user's A3W3)
            section = panel_section(r, panel, r.figure_seeds(fig), fig.gate_min_seeds)
            if section:
                r.add(section)
        extra = fig.extra and fig.extra(r, fig)
        if extra:
            r.add(extra)
    added = plan.scope.posthoc and posthoc_section(r, plan.scope.posthoc, plan.scope.planning_sd,
                                                   not plan.window_eval)
    if added:
        r.add(added)
    scale_rows = "\n".join(f"| {k} | {v} |" for k, v in SCALES[scale].items())
    timing = ", ".join(f"{k} {v / 60:.1f} min" for k, v in elapsed.items())
    archs = " and ".join(f"`{a}`" for a in tl_architectures())  # as the catalogue mixes them
    header = f"""# Reproduction report — scale `{scale}`

Made by:

```
{command}
```

Seeds: {seeds} per configuration ({first}..{first + seeds - 1}); curves are means over seeds with 95% CI bands
(Student t). Wall time of the phases run by this invocation:
{timing or 'none (report rebuilt from existing runs)'}.

{metric_text(plan)}
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
({archs}; MEDC needs only their actions, so one run uses both). Each
bundle's own evaluation (128 finished episodes, greedy and sampled, against a random team on
the same episodes; target localization is judged greedy, fleet and maze sampled):

{expert_table(plan.models) or "(no expert bundles found)"}
{expert_quality(r, plan)}
R_S of each expert follows the Models Manager contract's QoS rule (`medc_training.qos`) with
equal reputations (0.5): D_m is the mean |ΔE_i| over the environment attributes the expert and
the run both name (agents, walls, grid, step limit; the last two differ by 0 here), no expert
matches a run exactly (D_m = 0), and one without attributes (random, biased) counts as one unit
off in one of them.

"""
    protocol = out / plan.scope.protocol
    if protocol.exists():  # fixed before the runs it governs; see its first line
        header += "## Protocol\n\n" + protocol.read_text().strip() + "\n\n"
    header += f"**Verdicts.** {r.verdict_counts()} (each listed under its figure below).\n\n"
    notes = out / "discussion.md"
    if notes.exists():  # hand-written interpretation, kept across regenerations of the report
        header += "## Discussion\n\n" + notes.read_text().strip() + "\n\n## Figures and claims\n\n"
    return r.write(header)
