"""Rendering: the report's markdown (its header, each panel's section with its plot, the tables)
from what the finder read, the reference play measured and the judge decided. The prose is fixed
wording around numbers and verdicts."""

from __future__ import annotations

from pathlib import Path

from medc_training.stats import learning_score, mean_ci

from ..catalogue import OTHER_EVAL, OTHER_GRID, OTHER_MAX_STEPS, tl_architectures
from ..figures import Panel
from ..plan import Plan
from .reference_play import controller_lengths
from .references import reference_text, speed_section, versus_best, versus_reference


def methods_table(data: dict, wall: bool = False) -> str:
    """One row per series of a panel (``data``: label -> (steps, curves, summaries)): seeds, learning
    score and final episode length with 95% CIs, and with ``wall`` the mean training wall time."""
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


def panel_section(r, panel: Panel, seeds: tuple[int, ...] | None = None,
                  gate_min_seeds: int | None = None) -> str | None:
    """A panel's plot and section (its table, gate and claims), or None when none of its runs exist
    (``r``: the :class:`.build.Report` being built; ``seeds``: only those seeds are read;
    ``gate_min_seeds``: the gate's need, None: the scope's)."""
    from ..report_plots import plot_methods

    data: dict = {}
    for s in panel.series:
        data.update(r.series({s.label: s.run.name}, s.csv, seeds))
    if not data:
        return None
    refs = r.references(panel.gate.walls, panel.grid)
    plot_methods({k: (v[0], v[1]) for k, v in data.items()}, r.out / panel.png, panel.title, panel.ylabel,
                 references={k: (v["length"], v["length_ci"]) for k, v in refs.items()} or None)
    table = methods_table(data, wall=panel.wall)
    lines = [r.judge.gate(panel.gate.name, gate_min_seeds, seeds)]
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
            lines.append(r.judge.claim(c.text, c.better.key, c.worse.key, gate=panel.gate.name, **rules))
        else:
            lines.append(r.judge.claim_no_worse(c.text, c.better.key, c.worse.key, c.margin,
                                                gate=panel.gate.name, **rules))
    text = f"{panel.heading}\n\n![{panel.alt}]({panel.png})\n\n{table}\n\n" + "\n".join(lines)
    return text + (f"\n\n{panel.note}" if panel.note else "")


def wall_time_ratio(ratios: list[tuple[str, float]]) -> str:
    """Fig. 8's closing section: RS's training wall time over sparse's, per team (``ratios``)."""
    measured = ", ".join(f"{x:.2f} ({team})" for team, x in ratios)
    return ("### RS wall-time overhead\n\n- **The paper: RS needed double the wall time of sparse** — "
            f"here RS / sparse training wall time = {measured} ("
            "measured in the same worker pool, so it is noisy on a shared machine; `medc-bench train` "
            "gives a cleaner figure). The BFS distance field is computed once per episode on reset, so "
            "shaping costs little: the paper's 2x is not expected here, by design.")


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


def expert_quality(r, plan: Plan) -> str:
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


def header(r, plan: Plan, elapsed: dict) -> str:
    """Everything above the figures: how the report was made, the metric, the scale, the experts,
    the protocol (when the folder holds one), the verdict counts and the hand-written discussion
    (``r``: the :class:`.build.Report` whose figures were written; ``elapsed``: seconds per stage
    run by this invocation)."""
    from medc_training.config import SCALES

    out, scale, seeds, command = r.out, r.scale, r.seeds, r.command
    first = plan.scope.first_seed
    budget = plan.budget
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
    header += f"**Verdicts.** {r.judge.verdict_counts()} (each listed under its figure below).\n\n"
    notes = out / "discussion.md"
    if notes.exists():  # hand-written interpretation, kept across regenerations of the report
        header += "## Discussion\n\n" + notes.read_text().strip() + "\n\n## Figures and claims\n\n"
    return header
