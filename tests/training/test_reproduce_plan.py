"""medc-reproduce (medc_lab): the plan matches the paper's figures; verdicts are honest."""

import json
from pathlib import Path

import pytest
from medc_lab.catalogue import FRL_USERS, SIX
from medc_lab.plan import Plan
from medc_lab.report.judge import verdict
from medc_training.cli.train import parse_users
from medc_training.stats import compare, t95


def _plan(tmp_path, seeds=2):
    return Plan("cpu", seeds, tmp_path / "out", Path("models"))


def test_fig6_runs_free_complex_and_combined_experts_against_sparse(tmp_path):
    jobs = _plan(tmp_path).jobs("fig6")
    names = {j["name"] for j in jobs}
    for w in (2, 3):
        for run in ("sparse", "medc-free", "medc-complex", "medc-combined"):
            assert {f"A3W{w}-{run}/seed0", f"A3W{w}-{run}/seed1"} <= names
    combined = next(j for j in jobs if j["name"] == "A3W2-medc-combined/seed0")
    assert [Path(e).stem for e in combined["experts"]] == ["A1W0", "A1W3"]


def test_fig8_uses_the_papers_six_experts_and_eight_frl_users(tmp_path):
    jobs = _plan(tmp_path, seeds=1).jobs("fig8")
    medc = next(j for j in jobs if j["name"] == "A3W2-medc-six/seed0")
    assert tuple(Path(e).stem for e in medc["experts"]) == SIX
    frl = next(j for j in jobs if j["name"] == "A3W2-frl8/seed0")
    assert [(u["agents"], u["walls"]) for u in frl["config"]["frl_users"]] == list(FRL_USERS)


def test_fig9_has_three_faulty_users_in_medc_and_frl(tmp_path):
    jobs = _plan(tmp_path, seeds=1).jobs("fig9")
    medc = next(j for j in jobs if j["name"] == "A3W2-medc-six-3faulty/seed0")
    faulty = [e for e in medc["experts"] if e in ("random", "biased:0") or e.startswith("malicious:")]
    assert len(faulty) == 3 and len(medc["experts"]) == 6
    frl = next(j for j in jobs if j["name"] == "A3W2-frl8-3faulty/seed0")
    faults = sorted(u["fault"] for u in frl["config"]["frl_users"] if "fault" in u)
    assert faults == ["biased", "malicious", "random"]


def test_verdicts_need_the_ci_to_exclude_zero():
    assert verdict([10.0, 11.0, 10.5], [20.0, 21.0, 20.5]) == "held"
    assert verdict([10.0, 30.0], [20.0, 21.0]).startswith("not resolved (means lean the paper's way")
    assert verdict([12.0, 30.0], [10.0, 11.0]).startswith("not resolved (means lean against")
    assert verdict([25.0, 26.0, 25.5], [20.0, 21.0, 20.5]).startswith("contradicted")
    assert verdict([50.0, 50.0], [50.0, 50.0]) == "no difference"
    c = compare([1.0, 3.0], [2.0, 2.0])
    assert c["diff"] == pytest.approx(0.0) and c["half"] == pytest.approx(t95(1) * 1.0)


def test_frl_user_list_parsing():
    assert parse_users("A1W0,A3W2:malicious") == [{"agents": 1, "walls": 0},
                                                  {"agents": 3, "walls": 2, "fault": "malicious"}]
    with pytest.raises(ValueError, match="AyWz"):
        parse_users("A3W2:sneaky")


def test_long_supplement_names_carry_their_step_count(tmp_path):
    plan = Plan("cpu", 4, tmp_path / "out", Path("models"), {"long_steps": 1_000_000})
    jobs = plan.jobs("long")
    assert len(jobs) == 9  # at most 3 seeds x (sparse, MEDC six, MEDC oracle)
    assert {j["name"].split("/")[0] for j in jobs} == {
        "long1M-A3W2-sparse", "long1M-A3W2-medc-six", "long1M-A3W2-medc-oracle"}
    assert all(j["config"]["total_steps"] == 1_000_000 for j in jobs)


def test_device_reaches_every_run_and_bad_devices_are_refused(tmp_path):
    plan = Plan("paper", 1, tmp_path / "out", Path("models"), device="cuda:0")
    jobs = plan.jobs("fig8") + plan.expert_jobs(retrain=True)
    assert jobs and all(j["config"]["device"] == "cuda:0" for j in jobs)
    assert all(j["config"]["device"] == "cpu" for j in _plan(tmp_path).jobs("fig6"))
    with pytest.raises(ValueError, match="device"):
        Plan("cpu", 1, tmp_path / "out", Path("models"), device="tpu")


def test_fleet_and_maze_run_on_the_papers_10x10_grid_with_sampled_evaluation(tmp_path):
    from medc_lab.catalogue import OTHER_GRID, OTHER_MAX_STEPS

    plan = _plan(tmp_path, seeds=1)
    jobs = plan.jobs("fig10")
    assert {j["config"]["env"] for j in jobs} == {"fleet_coordination", "maze_cleaning"}
    for job in jobs:
        cfg = job["config"]
        assert (cfg["grid"], cfg["max_steps"]) == (OTHER_GRID, OTHER_MAX_STEPS) == (10, 400)
        assert cfg["eval_greedy"] is False
        # every evaluation environment can finish at least one full-length episode
        assert cfg["eval_steps"] // cfg["eval_envs"] >= cfg["max_steps"]
    paper = Plan("paper", 1, tmp_path / "paper", Path("models")).jobs("fig10")
    assert {j["config"]["eval_every"] for j in paper} == {40_000}  # the paper's interval
    # maze cleaning (its runs, FRL users and experts) on the ego9 window; fleet on the maps
    for job in jobs:
        options = [job["config"]["env_options"], *(u["env_options"] for u in job["config"]["frl_users"])]
        wanted = "ego9" if job["config"]["env"] == "maze_cleaning" else None
        assert {o.get("observation") for o in options} == {wanted}
    for job in plan.other_expert_jobs(retrain=True):
        wanted = "ego9" if job["config"]["env"] == "maze_cleaning" else None
        assert job["config"]["env_options"].get("observation") == wanted


def test_app_filter_plans_only_the_named_fleet_or_maze_application(tmp_path):
    maze = Plan("cpu", 1, tmp_path / "out", Path("models"), other_seeds=3, apps=["maze_cleaning"])
    jobs = maze.jobs("fig10")
    assert {j["config"]["env"] for j in jobs} == {"maze_cleaning"}
    assert {j["name"].split("/")[1] for j in jobs} == {"seed0", "seed1", "seed2"}
    assert len(jobs) == 7 * 3  # sparse, MEDC, FRL, IL; MEDC, FRL, IL with 3 faulty
    experts = maze.other_expert_jobs(retrain=True)
    assert len(experts) == 6 and {j["config"]["env"] for j in experts} == {"maze_cleaning"}
    # target localization is not affected by the filter
    assert maze.jobs("fig8") == Plan("cpu", 1, tmp_path / "out", Path("models")).jobs("fig8")
    with pytest.raises(ValueError, match="unknown application"):
        Plan("cpu", 1, tmp_path / "out", Path("models"), apps=["fleet"])
    # the shipped maze bundles are ego9 DAgger clones: reused for ego9, retrained for the maps
    shipped = Plan("cpu", 1, tmp_path / "out", Path("models"), apps=["maze_cleaning"])
    again = dict(name="maze-A1C0", env="maze_cleaning", agents=1, arch="mlp", steps=128_000, retrain=False,
                 max_steps=400, grid=10)
    assert shipped._expert_job(**again, env_options={"complexity": 0.0, "observation": "ego9"}) is None
    assert shipped._expert_job(**again, env_options={"complexity": 0.0})


def test_medc_train_flags_reach_the_config():
    from medc_training.cli.train import build_parser, config_from_args

    args = build_parser().parse_args(["--out", "x", "--lr", "0.001", "--eval-sampled", "--eval-envs", "8",
                                      "--env", "maze_cleaning", "--env-option", "complexity=1"])
    cfg = config_from_args(args)
    assert (cfg.lr, cfg.eval_greedy, cfg.eval_envs, cfg.env_options) == (0.001, False, 8, {"complexity": 1})
    assert config_from_args(build_parser().parse_args(["--out", "x"])).eval_greedy is True


def test_long_other_supplement_pits_medc_against_sparse_and_il_truthful_and_faulty(tmp_path):
    plan = Plan("cpu", 4, tmp_path / "out", Path("models"), {"long_steps": 1_000_000})
    jobs = plan.jobs("long-other")
    assert len(jobs) == 30  # 2 applications x 3 seeds x (sparse, MEDC, IL, MEDC-3faulty, IL-3faulty)
    assert {j["name"].split("/")[0] for j in jobs} == {
        f"long1M-{app}-{m}" for app in ("fleet", "maze")
        for m in ("sparse", "medc", "il", "medc-3faulty", "il-3faulty")}
    medc = next(j for j in jobs if j["name"] == "long1M-maze-medc/seed0")
    assert len(medc["experts"]) == 6
    assert [Path(e).stem for e in medc["experts"]][:2] == ["maze-A1C0", "maze-A2C0"]
    faulty = next(j for j in jobs if j["name"] == "long1M-fleet-il-3faulty/seed2")["experts"]
    assert faulty[:2] == ["random", "biased:0"] and faulty[2].startswith("malicious:")
    assert [Path(e).stem for e in faulty[3:]] == ["fleet-A1C8", "fleet-A3C4", "fleet-A2C8"]
    # the same faulty set as Fig. 11 at 100k steps
    fig11 = next(j for j in plan.jobs("fig10") if j["name"] == "fleet-il-3faulty/seed0")["experts"]
    assert fig11 == faulty
    assert all(j["config"]["total_steps"] == 1_000_000 and j["config"]["grid"] == 10 for j in jobs)


def test_experts_are_dagger_clones_retrained_unless_an_equal_dagger_bundle_exists(tmp_path):
    from medc_lab.catalogue import TL_EXPERTS
    from medc_training.bundle import load_bundle, read_manifest
    from medc_training.jobs import run_job

    models = tmp_path / "models"
    plan = Plan("cpu", 1, tmp_path / "out", models)
    jobs = plan.expert_jobs(retrain=False) + plan.other_expert_jobs(retrain=False)
    assert len(jobs) == len(TL_EXPERTS) + 1 + 12 and {j["kind"] for j in jobs} == {"clone"}
    assert {j["config"]["arch"] for j in jobs[: len(TL_EXPERTS)]} == {"lenet5", "mlp"}
    fleet = [j for j in jobs if j["config"]["env"] == "fleet_coordination"]
    assert all(j["config"]["eval_greedy"] is False and j["config"]["grid"] == 10 for j in fleet)
    # The shipped bundles were made by DAgger at these settings, so nothing is retrained ...
    shipped = Plan("cpu", 1, tmp_path / "out", Path("models"))
    assert shipped.expert_jobs(retrain=False) + shipped.other_expert_jobs(retrain=False) == []
    assert read_manifest("models/team/A3W2.safetensors")["training"]["method"] == "dagger"
    # ... and a tiny version of one job writes its bundle to models/, not to the report folder.
    job = jobs[0]
    job["config"].update(grid=7, max_steps=10, total_steps=64, num_envs=8, rollout_len=8, grad_steps=2,
                         eval_episodes=8, eval_envs=8)
    summary = run_job(job)
    assert summary["steps"] == 64
    assert load_bundle(job["bundle_to"]).manifest["training"]["method"] == "dagger"
    assert not (Path(job["out"]) / "policy.safetensors").exists()
    assert (Path(job["out"]) / "metrics.csv").exists()
    # The report's expert table reads the bundle's own evaluation from its manifest.
    from medc_lab.report.markdown import expert_table

    (models / "team").mkdir()
    (models / "team" / "broken.safetensors").write_bytes(b"not a bundle")
    rows = expert_table(models).splitlines()
    assert rows[2].startswith(f"| experts/{Path(job['bundle_to']).stem} | mlp | dagger 64 | ")
    assert rows[3].startswith("| team/broken | ? | no DAgger evaluation in manifest")
    # An equal DAgger bundle is reused; one made for another grid is retrained.
    again = dict(name="A1W0", env="target_localization", agents=1, arch="lenet5", steps=64, retrain=False)
    assert plan._expert_job(**again, grid=7, max_steps=10) is None
    assert plan._expert_job(**again, grid=9, max_steps=10)


def _fake_runs(out, name, finals, cfg):
    """Run folders whose evaluation curves fall from 20 to ``finals[seed]``."""
    from medc_training.metrics import CSV_COLUMNS

    for seed, final in enumerate(finals):
        d = out / "runs" / name / f"seed{seed}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps({"config": {**cfg, "seed": seed}, "train_seconds": 1.0}))
        rows = [{"step": i * 10, "episode_length": 20 - (20 - final) * min(1.0, i / 3)} for i in range(6)]
        with (d / "metrics.csv").open("w") as f:
            f.write(",".join(CSV_COLUMNS) + "\n")
            for r in rows:
                f.write(",".join(str(r.get(c, "")) for c in CSV_COLUMNS) + "\n")


def test_learnability_gate_blocks_claims_where_sparse_did_not_learn(tmp_path):
    from medc_lab.report.build import Report
    from medc_lab.report.judge import learnability_gate
    from medc_training.config import TrainConfig

    cfg = TrainConfig(agents=1, walls=0, grid=6, max_steps=20, eval_envs=8, observation="maps").to_dict()
    _fake_runs(tmp_path, "learned-sparse", [3.0, 4.0, 3.5], cfg)
    _fake_runs(tmp_path, "flat-sparse", [20.0, 19.0, 21.0], cfg)
    _fake_runs(tmp_path, "two-seeds-sparse", [3.0, 4.0], cfg)
    _fake_runs(tmp_path, "medc", [0.5, 0.6, 0.55], cfg)
    learned = learnability_gate(tmp_path, "learned-sparse")
    assert learned["passed"] and learned["n"] == 3 and learned["random"] > 5.0
    assert learned["diff"] == pytest.approx(3.5 - learned["random"])
    assert not learnability_gate(tmp_path, "flat-sparse")["passed"]  # no better than random play
    assert not learnability_gate(tmp_path, "two-seeds-sparse")["passed"]  # fewer than 3 seeds
    assert json.loads((tmp_path / "random_play.json").read_text())  # random play is measured once
    r = Report(tmp_path, "cpu", 3, "test")
    r.series({"a": "medc", "b": "learned-sparse", "c": "flat-sparse"})
    assert "— held" in r.judge.claim("medc beats sparse", "medc", "learned-sparse", gate="learned-sparse")
    blocked = r.judge.claim("medc beats sparse", "medc", "flat-sparse", gate="flat-sparse")
    assert "not testable (MDRL-sparse did not pass the learnability gate" in blocked
    assert "NOT passed" in r.judge.gate("flat-sparse") and "passed" in r.judge.gate("learned-sparse")
    assert r.judge.verdict_counts() == "2 claims: 1 held, 1 not testable"
    # A scope that judges a claim only once each side has its seeds: fewer read "incomplete".
    from medc_lab.catalogue import Scope

    _fake_runs(tmp_path, "medc-two-seeds", [0.5, 0.6], cfg)
    strict = Report(tmp_path, "cpu", 3, "test", Scope(claim_min_seeds=3))
    strict.series({"a": "medc", "b": "learned-sparse", "c": "medc-two-seeds"})
    judge = strict.judge
    assert "— held" in judge.claim("medc beats sparse", "medc", "learned-sparse", gate="learned-sparse")
    partial = judge.claim("medc beats sparse", "medc-two-seeds", "learned-sparse", gate="learned-sparse")
    assert "— incomplete (2 and 3 of 3 seeds ran; no verdict yet)" in partial
    no_worse = strict.judge.claim_no_worse("no worse", "medc-two-seeds", "learned-sparse", 1.0,
                                     gate="learned-sparse")
    assert "— incomplete (2 and 3 of 3 seeds ran" in no_worse
    assert strict.judge.verdict_counts() == "3 claims: 1 held, 2 incomplete"


def test_a_reproduction_keeps_the_evaluator_its_runs_were_made_with(tmp_path):
    """The committed reproduction was evaluated with the legacy window: rerunning its commands plans
    window runs (eval_episodes 0, written out), so its report never mixes two evaluators; a fresh
    folder plans fixed-episode runs; a folder holding both is refused."""
    committed = Plan("cpu", 3, Path("docs/reproduction"), Path("models"), {"long_steps": 1_000_000})
    jobs = committed.jobs("fig6") + committed.jobs("fig10") + committed.jobs("long-other")
    assert committed.window_eval and all(j["config"]["eval_episodes"] == 0 for j in jobs)
    fresh = _plan(tmp_path)
    jobs = fresh.jobs("fig6") + fresh.jobs("fig10")
    assert not fresh.window_eval and all(j["config"]["eval_episodes"] > 0 for j in jobs)
    for name, episodes in (("old", None), ("new", 64)):
        d = tmp_path / "out" / "runs" / name / "seed0"
        d.mkdir(parents=True)
        config = {"seed": 0} if episodes is None else {"seed": 0, "eval_episodes": episodes}
        (d / "summary.json").write_text(json.dumps({"config": config}))
        if name == "old":
            assert _plan(tmp_path).window_eval
    with pytest.raises(ValueError, match="mixes evaluators"):
        _plan(tmp_path)


def test_claims_scale_plans_the_protocol_regime_seeds_and_panels(tmp_path):
    """docs/reproduction/claims/PROTOCOL.md: realistic 40x40, 2 walls, 50 steps, seeds 300-304,
    250k steps, evaluation every 16,384 steps on 64 episodes; 15 configurations; its own experts
    (realistic, 128k DAgger steps), no shipped team, no fleet/maze runs."""
    plan = Plan("claims", 5, tmp_path / "out", tmp_path / "models")
    jobs = [j for phase in ("fig6", "fig7", "fig8", "fig9") for j in plan.jobs(phase)]
    unique = {j["name"]: j for j in jobs}
    assert len({n.split("/")[0] for n in unique}) == 15 and len(unique) == 75
    for job in unique.values():
        c = job["config"]
        assert c["seed"] in range(300, 305) and c["walls"] == 2 and c["grid"] == 40
        budget = (c["max_steps"], c["total_steps"], c["eval_every"], c["eval_episodes"])
        assert budget == (50, 250_000, 16_384, 64)
        assert c["env_options"] == {"sensing": "realistic"} and c["observation"] == "ego6+estimate"
    experts = plan.expert_jobs(retrain=False)
    names = ("A1W0", "A1W3", "A3W0", "A2W1", "A2W2", "A2W3", "A3W1")
    assert sorted(j["name"] for j in experts) == sorted(f"expert {n}" for n in names)
    for job in experts:
        assert job["config"]["env_options"] == {"sensing": "realistic"} and job["config"]["grid"] == 40
        assert job["config"]["total_steps"] == 128_000
    assert plan.other_expert_jobs(retrain=False) == []


def test_a_wide_unresolved_claim_is_labelled_under_powered():
    wide_a, wide_b = [10.0, 30.0, 20.0, 12.0, 28.0], [18.0, 22.0, 35.0, 9.0, 25.0]
    assert "under-powered" in verdict(wide_a, wide_b, underpowered=5.9)
    assert "under-powered" not in verdict(wide_a, wide_b)
    assert verdict([1.0, 1.1, 0.9], [5.0, 5.1, 4.9], underpowered=5.9) == "held"


def test_references_compare_final_policies_and_steps_to_sparses_level(tmp_path):
    from medc_lab.report.references import (
        load_references,
        speed_section,
        steps_to_level,
        versus_reference,
    )

    for policy, length in (("random", 48.0), ("greedy", 20.0), ("infotaxis", 18.0)):
        lengths = [length - 1, length + 1] * 256
        (tmp_path / f"{policy}.json").write_text(json.dumps(
            {"policy": policy, "lengths": lengths, "successes": [1.0] * len(lengths)}))
    refs = load_references(tmp_path)
    assert refs["infotaxis"]["episodes"] == 512 and refs["infotaxis"]["length"] == 18.0
    # final level = mean of the last three evaluations; the best controller is infotaxis, not random
    good = [[40.0, 12.0, 11.0, 10.0], [40.0, 12.5, 11.5, 10.5], [40.0, 11.5, 10.5, 9.5]]
    assert "beats infotaxis" in versus_reference("team", good, refs)
    bad = [[40.0, 30.0, 30.0, 30.0], [40.0, 31.0, 31.0, 31.0], [40.0, 29.0, 29.0, 29.0]]
    assert "does not beat infotaxis" in versus_reference("team", bad, refs)
    assert steps_to_level([0, 10, 20], [50.0, 30.0, 20.0], 25.0) == 20.0
    assert steps_to_level([0, 10, 20], [50.0, 30.0, 26.0], 25.0) is None
    steps = [0, 100, 200, 300, 400, 500]  # sparse's final level: 20 (its last three evaluations)
    data = {"sparse": (steps, [[50.0, 45.0, 30.0, 20.0, 20.0, 20.0]] * 3),
            "medc": (steps, [[50.0, 20.0, 20.0, 20.0, 20.0, 20.0]] * 3)}
    line = speed_section(data, "sparse")
    assert "(20.00 steps per episode" in line
    assert "sparse: 300 steps (3 of 3 seeds), ratio to sparse 1.00" in line
    assert "medc: 100 steps (3 of 3 seeds), ratio to sparse 0.33" in line
