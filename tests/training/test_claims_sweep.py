"""The when-do-experts-help sweep (docs/reproduction/claims/SWEEP.md): planned only in the claims
scope, sharing its protocol cell with Figs. 6 and 8; its report section computed from the runs."""

import dataclasses
import json
import math
from pathlib import Path

import pytest
from medc_lab.catalogue import PHASES, SCOPES, SIX
from medc_lab.figures import SweepCell, sweep
from medc_lab.plan import Plan
from medc_lab.report.build import Report, closing_section
from medc_lab.report.finder import report_figures
from medc_lab.report.markdown import panel_section
from medc_lab.report.reference_play import CONTROLLER_PLAY, episodes_key, random_play, random_play_length
from medc_lab.report.sweep import CellResult, compare_lower, guided_share, within
from medc_training.metrics import CSV_COLUMNS
from medc_training.stats import t95

SEEDS = (300, 301, 302)
MEDC = "A3W2-medc-six"
SPARSE = "A3W2-sparse"


def _claims(tmp_path, seeds=3):
    return Plan("claims", seeds, tmp_path / "out", tmp_path / "models")


def test_the_sweep_plans_its_36_runs_and_shares_the_protocol_cell(tmp_path):
    plan = _claims(tmp_path, seeds=5)
    jobs = plan.jobs("sweep")
    configs = {j["name"].split("/")[0]: j["config"] for j in jobs}
    setting = {n: (c["method"], c["grid"], c["expert_rate"], c["q_threshold"]) for n, c in configs.items()}
    assert setting == {
        "sweep-g24-A3W2-sparse": ("sparse", 24, 0.1, 0.05),
        "sweep-g32-A3W2-sparse": ("sparse", 32, 0.1, 0.05),
        SPARSE: ("sparse", 40, 0.1, 0.05),
        **{f"sweep-g{g}-A3W2-medc-six-re{r}": ("medc", g, r, 0.05)
           for g in (24, 32, 40) for r in (0.1, 0.3, 0.6) if (g, r) != (40, 0.1)},
        MEDC: ("medc", 40, 0.1, 0.05),
        "sweep-g40-A3W2-medc-six-q0.01": ("medc", 40, 0.1, 0.01),
        "sweep-g40-A3W2-medc-six-q0.2": ("medc", 40, 0.1, 0.2),
    }
    # 3 seeds (300-302) even when 5 are asked for; 12 new configurations = 36 new runs
    protocol_cell = sorted(j["name"] for j in jobs if j["name"].startswith(f"{MEDC}/"))
    assert protocol_cell == [f"{MEDC}/seed{s}" for s in SEEDS]
    assert len(jobs) == 14 * 3 and sum(j["name"].startswith("sweep-") for j in jobs) == 36
    for job in jobs:
        c = job["config"]
        assert (c["walls"], c["agents"], c["max_steps"], c["total_steps"]) == (2, 3, 50, 250_000)
        evaluation = (c["eval_every"], c["eval_episodes"], c["env_options"])
        assert evaluation == (16_384, 64, {"sensing": "realistic"})
        experts = [Path(e).stem for e in job["experts"]]
        assert experts == (list(SIX) if c["method"] == "medc" else [])
        assert all(str(tmp_path / "models" / "experts") in e for e in job["experts"])
    # the protocol's cell and its sparse are Fig. 8's and Fig. 6's jobs: a finished one is skipped
    borrowed = {j["name"]: j for j in plan.jobs("fig8") + plan.jobs("fig6")}
    for job in jobs:
        if not job["name"].startswith("sweep-"):
            other = borrowed[job["name"]]
            assert job["fig"] == "sweep" and other["fig"] != "sweep"
            assert {**job, "fig": ""} == {**other, "fig": ""}


def test_no_other_scale_plans_the_sweep(tmp_path):
    for scale in ("cpu", "paper"):
        plan = Plan(scale, 3, tmp_path / scale, Path("models"))
        assert plan.jobs("sweep") == []
        everything = [j["name"] for phase in PHASES[1:] for j in plan.jobs(phase)]
        assert everything == [j["name"] for phase in PHASES[1:-1] for j in plan.jobs(phase)]
        assert not any(n.startswith("sweep-") for n in everything)
    assert PHASES[-1] == "sweep" and SCOPES["claims"].sweep and not SCOPES["cpu"].sweep


def test_run_options_are_refused_unless_they_are_config_fields(tmp_path):
    from medc_lab.figures import Run

    plan = _claims(tmp_path)
    assert plan.run_config(Run("x", "sparse", options=(("grid", 24),)), 300, 10)["grid"] == 24
    with pytest.raises(ValueError, match="not TrainConfig fields"):
        plan.run_config(Run("x", "sparse", options=(("grids", 24),)), 300, 10)


def test_guided_share_is_weighted_by_the_steps_each_row_covers():
    rows = [{"step": 0, "expert_step_fraction": 0.0, "expert_follow_rate": 0.0},
            {"step": 100, "expert_step_fraction": 0.1, "expert_follow_rate": 1.0},
            {"step": 200, "expert_step_fraction": math.nan, "expert_follow_rate": math.nan},
            {"step": 400, "expert_step_fraction": 0.4, "expert_follow_rate": 0.5}]
    share, follow = guided_share(rows)
    # (0.1 x 100 + 0.4 x 200) / 300; follow: (1.0 x 10 + 0.5 x 80) / 90
    assert share == pytest.approx(0.3) and follow == pytest.approx(50 / 90)
    assert all(math.isnan(x) for x in guided_share(rows[:1]))


# ---------------------------------------------------------------- the report section
STEPS = (0, 100, 200, 300, 400, 600)   # the budget is 600 steps
FLAT = (0.0,) * 6


def _curve(values, delta):
    return [v + delta for v in values]


#: run name -> (per-seed curve (or one curve for every seed), per-seed offset, expert_step_fraction,
#: expert_follow_rate); offsets -1, 0, +1 give each arm an SD of 1 over its 3 seeds.
SPREAD = (-1.0, 0.0, 1.0)
RUNS = {
    "sweep-g24-A3W2-sparse": ((50, 50, 40, 20, 20, 20), SPREAD, FLAT, FLAT),
    "sweep-g24-A3W2-medc-six-re0.1": ((50, 20, 20, 15, 15, 15), SPREAD, (0.0, 0.1, 0.1, 0.2, 0.2, 0.4),
                                      (0.0, 1.0, 1.0, 0.5, 0.5, 0.5)),
    "sweep-g32-A3W2-sparse": ((50.5, 50, 50, 50, 50, 50), (0.0,) * 3, FLAT, FLAT),
    "sweep-g32-A3W2-medc-six-re0.1": ((50.5, 45, 40, 40, 40, 40), (0.0,) * 3, (0.1,) * 6, (1.0,) * 6),
    SPARSE: ((50, 50, 50, 30, 30, 30), SPREAD, FLAT, FLAT),
    MEDC: ((50, 15, 15, 15, 15, 15), SPREAD, (0.1,) * 6, (1.0,) * 6),
    "sweep-g40-A3W2-medc-six-re0.6": ((50, 40, 40, 40, 40, 40), SPREAD, (0.1,) * 6, (1.0,) * 6),
    "sweep-g40-A3W2-medc-six-q0.01": ((50, 32, 14, 14, 14, 14), SPREAD, (0.1,) * 6, (1.0,) * 6),
    "sweep-g40-A3W2-medc-six-q0.2": ((50, 40, 16, 16, 16, 16), SPREAD, (0.1,) * 6, (1.0,) * 6),
}


def _write_seed(out, name, seed, config, curve, fractions, follows):
    d = out / "runs" / name / f"seed{seed}"
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"config": {**config, "seed": seed}, "train_seconds": 1.0}))
    with (d / "metrics.csv").open("w") as f:
        f.write(",".join(CSV_COLUMNS) + "\n")
        for step, length, fraction, follow in zip(STEPS, curve, fractions, follows):
            row = {"step": step, "episode_length": length, "expert_step_fraction": fraction,
                   "expert_follow_rate": follow}
            f.write(",".join(str(row.get(c, "")) for c in CSV_COLUMNS) + "\n")


#: Random play on the gate's 16 fixed episodes of each sparse seed (length, success rate), cached
#: as if played: playing them on the realistic preset would take minutes.
RANDOM = {"sweep-g24-A3W2-sparse": ((40.0, 0.30), (41.0, 0.25), (39.0, 0.35)),
          "sweep-g32-A3W2-sparse": ((47.0, 0.15), (47.5, 0.15), (46.5, 0.15)),
          SPARSE: ((46.0, 0.10), (46.5, 0.09), (47.0, 0.08))}


#: The classical controllers on each run's evaluation episodes (per-episode lengths, repeated over
#: the 64 episodes), cached as if played: infotaxis 18 steps, greedy 20, gradient 42.
CONTROLLER_LENGTHS = {"infotaxis": (17, 19), "greedy": (19, 21), "gradient": (40, 44)}


def _sweep_folder(tmp_path, names=tuple(RUNS), episodes=16):
    """The sweep's runs of RUNS under tmp_path/out, with their planned configs at a 600-step
    budget; Fig. 6's sparse and Fig. 8's MEDC also have seeds 303 and 304 (far better), which the
    sweep must not read. Random play on ``episodes`` fixed episodes of each gate's seeds is cached
    (RANDOM; seeds 303 and 304 as seed 302), and so are the classical controllers on every run's
    evaluation episodes (CONTROLLER_LENGTHS)."""
    plan = _claims(tmp_path)
    configs = {j["name"].split("/")[0]: j["config"] for j in plan.jobs("sweep")}
    cache, controllers = {}, {}
    for name in names:
        curve, offsets, fractions, follows = RUNS[name]
        config = {**configs[name], "total_steps": STEPS[-1]}
        for seed in (*SEEDS, 303, 304):
            evals = config["eval_episodes"]
            controllers[episodes_key({**config, "seed": seed}, None)] = {
                n: {"lengths": list(v) * (evals // 2), "successes": [True] * evals}
                for n, v in CONTROLLER_LENGTHS.items()}
        for i, (seed, delta) in enumerate(zip(SEEDS, offsets)):
            _write_seed(plan.out, name, seed, config, _curve(curve, delta), fractions, follows)
            for extra in ((seed, 303, 304) if seed == 302 else (seed,)):
                if name in RANDOM:
                    length, success = RANDOM[name][i]
                    cache[episodes_key({**config, "seed": extra}, episodes)] = {
                        "episode_length": length, "success_rate": success}
        if name in (SPARSE, MEDC):
            for seed in (303, 304):
                _write_seed(plan.out, name, seed, config, [5.0] * 6, FLAT, FLAT)
    (plan.out / "random_play.json").write_text(json.dumps(cache))
    (plan.out / CONTROLLER_PLAY).write_text(json.dumps(controllers))
    reference = plan.out / "reference" / "g40w2t50"
    reference.mkdir(parents=True)
    (reference / "infotaxis.json").write_text(json.dumps(
        {"policy": "infotaxis", "lengths": [17.0, 19.0] * 8, "successes": [1.0] * 16}))
    return plan


def _report(plan):
    # the claims scope, with random play on 16 (not 256) fixed episodes (cached above)
    scope = dataclasses.replace(SCOPES["claims"], gate_random_episodes=16)
    return Report(plan.out, "claims", 5, "test", scope, plan.base)


def test_sweep_section_speed_ups_differences_guided_shares_and_hypotheses(tmp_path):
    plan = _sweep_folder(tmp_path)
    r = _report(plan)
    fig = sweep()
    assert [f.phase for f in report_figures(plan.out / "runs")][-1] == "sweep"
    panels = [panel_section(r, p, r.figure_seeds(fig), fig.gate_min_seeds) for p in fig.panels]
    # the panels: 3 seeds pass the sweep's gate (the scope needs 5); the 40x40 reference lines on
    # the 40x40 panel only; no claim is added to the protocol's verdicts
    assert "(A3W2-sparse) — passed" in panels[2] and "n = 3 seeds" in panels[2]
    assert "Reference lines" in panels[2] and "Reference lines" not in panels[0]
    # sparse's final levels 29, 30, 31 against infotaxis's 18 steps on the same episodes (SD 1)
    sd1 = t95(2) / math.sqrt(3)
    assert (f"MDRL-sparse: final 30.00 ± {sd1:.2f} steps, does not beat infotaxis (18.00 ± 0.00 on the "
            f"same episodes): +12.00 ± {sd1:.2f} (n = 3 seeds)") in panels[2]
    assert "(sweep-g32-A3W2-sparse) — NOT passed" in panels[1]
    assert r.judge.verdict_counts() == "no claims"
    text = closing_section(r, fig)
    assert r.judge.verdict_counts() == "no claims"
    assert (plan.out / "sweep.png").stat().st_size > 10_000
    half = t95(2) * math.sqrt(2 / 3)  # Welch: SD 1 in both arms, 3 seeds each
    assert f"{half:.2f}" == "3.51"
    # L_G at 24: the mean of the seeds' last three evaluations (19, 20, 21); the seed at 21 never
    # reaches 20 and counts the budget: sparse's steps (300 + 300 + 600) / 3 = 400
    assert "| 24×24 | 3 | passed: " in text and "| 20.00 | 400 (2 of 3 seeds reach it) |" in text
    # seeds 303 and 304 (at 5 steps) are not read: L_G at 40 is 30, not 20
    assert "| 30.00 | 400 (2 of 3 seeds reach it) |" in text
    assert "| 32×32 | 3 | NOT passed (needs ≥ 3 seeds and a CI below 0): not testable" in text
    # random play's success rate on the gate's episodes, the mean over the area's seeds
    assert "| 30% | 20.00 |" in text and "| 15% | 50.00 |" in text and "| 9% | 30.00 |" in text
    assert "| 40×40 | 3 | passed: -16.50 ± " in text  # 30 - (46 + 46.5 + 47) / 3
    rows = {line.split("`")[1]: line for line in text.splitlines() if line.count("`") == 2}
    # MEDC at 24: steps (100 + 100 + 300) / 3; speed-up 400 / 166.7 = 2.4, at least (a sparse seed
    # never reached L_G); scores 17 -/+ 1 vs 30 -/+ 1; guided (10 + 10 + 20 + 20 + 80) / 600,
    # follow (10 + 10 + 10 + 10 + 40) / 140
    assert rows["sweep-g24-A3W2-medc-six-re0.1"].endswith(
        "| 3 | ≥2.40× | 167 (3 of 3) | -13.00 ± 3.51 | 23.3% | 57% |")
    assert rows[MEDC].endswith("| 3 | ≥4.00× | 100 (3 of 3) | -23.00 ± 3.51 | 10.0% | 100% |")
    # no MEDC seed reaches 30 either: 400 / 600, bounded neither way
    tail = "| 10.0% | 100% |"
    assert rows["sweep-g40-A3W2-medc-six-re0.6"].endswith(f"| ?0.67× | 600 (0 of 3) | +2.00 ± 3.51 {tail}")
    assert rows["sweep-g40-A3W2-medc-six-q0.01"].endswith(f"| ≥2.00× | 200 (3 of 3) | -20.40 ± 3.51 {tail}")
    assert rows["sweep-g40-A3W2-medc-six-q0.2"].endswith(f"| ≥2.00× | 200 (3 of 3) | -17.20 ± 3.51 {tail}")
    assert rows["sweep-g32-A3W2-medc-six-re0.1"].startswith("| 32×32 (not testable) |")
    assert rows["sweep-g32-A3W2-medc-six-re0.1"].endswith(f"| 3 | 1.00× | 100 (3 of 3) | -9.00 ± 0.00 {tail}")
    assert rows["sweep-g24-A3W2-medc-six-re0.6"].endswith("| 0 | not run | | | | |")
    # H1: -23 + 3.51 < -13 - 3.51; H2: R_E 0.6's +2 is clearly above; H3: Q 0.01 (2.6 from -23)
    # lies within the CI of Q 0.05's, Q 0.2 (5.8 away) outside it but with overlapping CIs
    assert "- **H1 (rarity)** — supported:" in text
    assert "- **H2 (R_E binds)** — not supported:" in text
    assert "- **H3 (Q matters less than R_E)** — not resolved:" in text
    # numbers and verdicts only: no recommendation closes the section
    assert "buy experts" not in text and text.rstrip().endswith("their quality there is not measured.")


def test_random_play_keeps_the_success_rate_and_reads_old_length_only_entries(tmp_path):
    from medc_training.config import TrainConfig

    config = TrainConfig(agents=1, walls=0, grid=7, max_steps=10, eval_envs=8, eval_episodes=8,
                         observation="maps", seed=3).to_dict()
    key = episodes_key(config, None)
    (tmp_path / "random_play.json").write_text(json.dumps({key: 9.5}))  # written before success rates
    assert random_play_length(tmp_path, config) == 9.5  # read as it is, nothing played
    assert json.loads((tmp_path / "random_play.json").read_text()) == {key: 9.5}
    played = random_play(tmp_path, config)  # the success rate is asked for: played again, kept
    assert set(played) == {"episode_length", "success_rate"} and 0.0 <= played["success_rate"] <= 1.0
    assert json.loads((tmp_path / "random_play.json").read_text()) == {key: played}
    assert random_play_length(tmp_path, config) == played["episode_length"]


def test_hypothesis_rules_answer_from_the_cis():
    def cell(scores, sparse=(30.0, 30.0, 30.0)):
        from medc_lab.report.sweep import Area, Arm

        arm = Arm(steps=((0.0, 1.0),) * len(scores), curves=tuple((50.0, s) for s in scores),
                  budgets=(1.0,) * len(scores), guided=(0.1,) * len(scores), follow=(1.0,) * len(scores))
        base = Arm(steps=((0.0, 1.0),) * 3, curves=tuple((50.0, s) for s in sparse), budgets=(1.0,) * 3,
                   guided=(0.0,) * 3, follow=(0.0,) * 3)
        return CellResult(SweepCell(40, 0.1, 0.05, "m", "s"), arm, Area(40, "s", base, {"passed": True}, 0.1))

    low, high = cell((9.0, 10.0, 11.0)), cell((19.0, 20.0, 21.0))
    assert (compare_lower(low, high), compare_lower(high, low)) == ("supported", "not supported")
    assert compare_lower(low, cell((12.0, 13.0, 14.0))) == "not resolved"
    assert within(low, [cell((10.5, 11.0, 11.5)), cell((8.0, 9.0, 10.0))]) == "supported"
    assert within(low, [cell((10.5, 11.0, 11.5)), high]) == "not supported"
    assert cell((10.0, 30.0, 50.0)).underpowered and not low.underpowered


def test_no_sweep_section_or_figure_without_a_run_of_its_own(tmp_path):
    plan = _sweep_folder(tmp_path, names=(SPARSE, MEDC))  # Figs. 6 and 8 only
    assert "sweep" not in [f.phase for f in report_figures(plan.out / "runs")]
    r = _report(plan)
    fig = sweep()
    assert closing_section(r, fig) is None and not (plan.out / "sweep.png").exists()


def test_medc_reproduce_report_adds_the_sweep_after_the_protocols_figures(tmp_path, monkeypatch):
    from medc_lab.cli.reproduce import main

    plan = _sweep_folder(tmp_path, episodes=256)  # the claims scope's gate episodes
    monkeypatch.chdir(tmp_path)
    assert main(["--scale", "claims", "--seeds", "5", "--only", "report", "--out", "out",
                 "--models", "models"]) == 0
    report = (plan.out / "report.md").read_text()
    # the protocol's 13 claims (Figs. 6-9 on A3W2: only sparse and MEDC (6 experts) ran, so each is
    # "not run", Fig. 7's "at worst match" claims included), none of the sweep's; the sweep's
    # section last, after its three panels, on seeds 300-302 (Fig. 6 reads all 5)
    assert "**Verdicts.** 13 claims: 13 not run " in report
    assert "final episode length 20.00 vs random play 46.70 on 256 fixed episodes of each seed" in report
    assert "final episode length 30.00 vs random play 46.50 on 256 fixed episodes of each seed" in report
    assert report.index("### Fig. 9") < report.index("### Sweep — learning curves on 24×24 (A3W2)")
    # the sweep's section closes on its numbers: no recommendation is written
    assert report.rstrip().endswith("but their quality there is not measured.")
    assert "deciding whether to buy" not in report
    assert "### When do borrowed experts help? (sweep)" in report and (plan.out / "sweep.png").exists()
