"""The analysis a report adds after its protocol: paired by seed, power, Holm, non-inferiority by
its bound, censored speed-ups; and the committed claims report rebuilt from its runs, its
protocol's part unchanged."""

import dataclasses
import math
import os
import re
import shutil
from pathlib import Path

import pytest
from medc_lab.report.posthoc import analyse, changes, speed_table
from medc_training.stats import t95

REPO = Path(__file__).resolve().parents[2]
CLAIMS = REPO / "docs" / "reproduction" / "claims"
ADDED = "\n\n## Added after the protocol ("


def _record(text, first, second, margin=None, word="not resolved (means lean the paper's way)"):
    return {"text": text, "word": word, "margin": margin,
            "first": dict(enumerate(first, start=300)), "second": dict(enumerate(second, start=300))}


def test_analyse_pairs_by_seed_adjusts_by_holm_and_judges_non_inferiority_by_the_bound():
    records = [
        # differences -3 -1 -3 -3 -1 by seed: mean -2.2, SD sqrt(1.2)
        _record("A beats B", [27.0, 27.0, 30.0, 26.0, 30.0], [30.0, 28.0, 33.0, 29.0, 31.0]),
        _record("C beats B", [31.0, 27.0, 32.0, 28.0, 30.0], [30.0, 28.0, 33.0, 29.0, 31.0]),
        _record("not judged", [1.0], [2.0], word="not testable (gate)"),
        # mean +0.6 inside the 2-step margin, the CI's upper bound outside it
        _record("D at worst matches B", [30.0, 31.0, 34.0, 27.0, 32.0], [30.0, 28.0, 33.0, 29.0, 31.0],
                margin=2.0, word="held"),
    ]
    directional, non_inferior = analyse(records)
    assert [r["text"] for r in directional] == ["A beats B", "C beats B"]
    a, c = directional
    se = math.sqrt(1.2 / 5)
    assert a["paired"]["diff"] == pytest.approx(-2.2) and a["paired"]["half"] == pytest.approx(t95(4) * se)
    assert (a["paired"]["a_lower"], a["paired"]["n"]) == (5, 5)
    t = 2.2 / se  # df 4: P(|T| <= t) = t (t^2 + 6) / (t^2 + 4)^(3/2)
    p_a = 1 - t * (t * t + 6) / (t * t + 4) ** 1.5
    assert a["paired"]["p"] == pytest.approx(p_a, rel=1e-9)
    # Holm over the two directional claims: the smaller p doubled, the larger kept (or the running max)
    p_c = c["paired"]["p"]
    assert p_c > 2 * p_a
    assert a["paired_holm"] == pytest.approx(2 * p_a) and c["paired_holm"] == pytest.approx(p_c)
    # the protocol's (Welch) test on the same scores does not resolve it; its power at -2.2 is low
    assert a["welch"]["half"] > 2.2 and a["power"] < 0.5 < a["paired_power"]
    assert a["mdd"] > a["paired_mdd"]
    (d,) = non_inferior
    assert d["paired"]["diff"] == pytest.approx(0.6) and d["paired"]["diff"] + d["paired"]["half"] > 2.0
    lines = changes(directional, non_inferior)
    assert any(line.startswith("- **A beats B** (protocol: not resolved)") and "held paired by seed" in line
               for line in lines)
    assert any(line.startswith("- **D at worst matches B** (protocol: held): inconclusive by the bound")
               for line in lines)


def test_censored_speed_table_counts_non_reaching_seeds_at_the_budget():
    steps = [0.0, 100.0, 200.0, 300.0]
    budget = [{"config": {"total_steps": 400}}] * 2
    data = {
        # final level (mean of the last three evaluations) 10 and 12: level 11, reached at 200 and 300
        "sparse": (steps, [[50.0, 20.0, 5.0, 5.0], [50.0, 20.0, 15.0, 1.0]], budget),
        "medc": (steps, [[50.0, 10.0, 10.0, 10.0], [50.0, 40.0, 40.0, 40.0]], budget),
    }
    table = speed_table([("panel", data, "sparse")])
    # sparse: both reach 11, at 200 and 300: mean 250; medc: one at 100, one never (400): 250 counted,
    # 100 over the reaching seed alone; the ratio is a lower bound (medc's side is censored)
    assert "| panel | 11.00 | sparse | 2 of 2 | 250 | 250 | 1.00 |" in table
    assert "| panel | 11.00 | medc | 1 of 2 | 100 | 250 | ≥1.00 |" in table


def _header_inputs(report: str) -> tuple[str, dict]:
    """The command the committed report names and the wall time it states."""
    command = report.split("```\n")[1].strip()
    minutes = re.search(r"invocation:\n((?:\w+ [\d.]+ min(?:, )?)+)\.", report)
    elapsed = {k: float(v) * 60 for k, v in re.findall(r"(\w+) ([\d.]+) min", minutes.group(1))}
    return command, elapsed


def test_committed_claims_report_is_rebuilt_from_its_runs_with_the_protocols_part_unchanged(tmp_path,
                                                                                         monkeypatch):
    from medc_lab.plan import Plan
    from medc_lab.report import build_report

    report = (CLAIMS / "report.md").read_text()
    assert report.count(ADDED) == 1
    command, elapsed = _header_inputs(report)
    out = Path("docs/reproduction/claims")
    shutil.copytree(CLAIMS, tmp_path / out, ignore=shutil.ignore_patterns("*.png"))
    os.symlink(REPO / "models", tmp_path / "models")
    monkeypatch.chdir(tmp_path)
    plan = Plan("claims", 5, out, Path("models/claims"), {}, 2)
    assert build_report(out, "claims", 5, command, plan, elapsed).read_text() == report
    # without the added section the builder makes exactly the protocol's part: its verdicts and tables
    plan.scope = dataclasses.replace(plan.scope, posthoc=None)
    protocol_part = build_report(out, "claims", 5, command, plan, elapsed).read_text()
    assert protocol_part == report[:report.index(ADDED)] + "\n"
    # rebuilding played nothing new
    for name in ("random_play.json", "controller_play.json", "expert_eval.json", "SWEEP.md"):
        assert (tmp_path / out / name).read_text() == (CLAIMS / name).read_text()
