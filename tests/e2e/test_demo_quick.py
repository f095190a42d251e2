"""`make demo QUICK=1` end to end: the paper's time sequence on the embedded defaults.

Runs the real console script (registry on the in-process chain, local content store, MEDC and
sparse training, reviews, withdrawals, the ROS 2 graph as separate processes) and checks what a
user would look at: allocation by QoS, settled payments, updated reputations, a trained team
that beats random moves in the graph, and the report with its figures.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from ros_domain import claim_domain

pytestmark = [pytest.mark.slow, pytest.mark.ros]

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("demo")
    script = Path(sys.executable).parent / "medc-demo"
    env = dict(os.environ, ROS_DOMAIN_ID=str(claim_domain()))
    proc = subprocess.run([str(script), "--quick", "--no-progress", "--out", str(out)], capture_output=True,
                          text=True, timeout=900, env=env)
    assert proc.returncode == 0, f"medc-demo failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    last = proc.stdout.strip().splitlines()[-1]
    return json.loads(last), out


def test_allocation_follows_qos(demo: tuple[dict, Path]) -> None:
    summary, _ = demo
    allocs = summary["allocations"]
    assert len(allocs) == 3
    qos = [math.inf if a["qos"] == "inf" else a["qos"] for a in allocs]
    assert qos == sorted(qos, reverse=True), f"allocations not in QoS order: {qos}"
    for a, q in zip(allocs, qos):
        # Every owner and model starts at reputation 0.5: QoS = 0.5 * 0.5 / D_m.
        if a["distance"] > 0:
            assert q == pytest.approx(0.25 / a["distance"], rel=1e-6)
    # The requester's environment is A3W2: no shared expert (A1W0..A3W1, models/claims/experts) is
    # closer than D_m = 0.5.
    assert min(a["distance"] for a in allocs) == pytest.approx(0.5)


def test_payments_settle(demo: tuple[dict, Path]) -> None:
    summary, _ = demo
    paid = summary["paid_wei"]
    assert paid == sum(a["price_wei"] for a in summary["allocations"]) > 0
    assert sum(p["withdrawn_wei"] for p in summary["payments"]) == paid
    assert summary["models_manager_balance_wei"] == 0


def test_reviews_update_reputations(demo: tuple[dict, Path]) -> None:
    summary, _ = demo
    reps = {r["model"]: r for r in summary["model_reputations"]}
    assert len(summary["reviews"]) == 3
    for review in summary["reviews"]:
        rep = reps[review["model"]]
        assert rep["before"] == pytest.approx(0.5)
        # One allocation, one review: Rep_m = total review / allocation count = the review.
        assert rep["after"] == pytest.approx(review["review"], abs=1e-9)
    unallocated = set(reps) - {r["model"] for r in summary["reviews"]}
    assert unallocated and all(reps[m]["after"] == pytest.approx(0.5) for m in unallocated)


def test_graph_runs_trained_policies(demo: tuple[dict, Path]) -> None:
    summary, _ = demo
    new, team = summary["graph"], summary["graph_shipped_team"]
    assert not new["skipped"] and new["episodes"] == 5 and len(new["episode_lengths"]) == 5
    assert all(1 <= n <= 50 for n in new["episode_lengths"])
    # The classical searcher plays the new policy's episodes (the regime's 50-step cap) and finds the
    # source in fewer steps than random moves.
    searcher = summary["graph_searcher"]
    assert not searcher["skipped"] and searcher["policy"] == "infotaxis" and searcher["episodes"] == 5
    assert all(1 <= n <= 50 for n in searcher["episode_lengths"])
    assert searcher["mean_length"] < summary["random_policy_episode_length"]
    # The shipped team plays in the regime it was trained for and beats random moves there.
    assert not team["skipped"] and team["episodes"] == 5
    assert all(1 <= n <= 50 for n in team["episode_lengths"])
    assert team["mean_length"] < team["random_episode_length"]
    assert team["success_rate"] > 0.5
    # The field benchmark's world: the shipped benchmark team and the strongest searcher play the same
    # number of episodes there (the benchmark's 120-move cap), each finding the source.
    bench = summary["graph_benchmark"]
    assert not bench["skipped"] and bench["config"] == "models/radbench/g20-a3.yaml"
    assert bench["searcher_policy"] == "infotaxis-exact"
    for side in (bench["team"], bench["searcher"]):
        assert side["episodes"] == 5 and all(1 <= n <= 120 for n in side["episode_lengths"])
        assert side["success_rate"] > 0.5


def test_training_and_report(demo: tuple[dict, Path]) -> None:
    summary, out = demo
    for method in ("medc", "sparse"):
        run = summary["training"][method]
        assert run["steps"] >= 40_960
        assert 1 <= run["final_episode_length"] <= 50
        assert (out / method / "policy.safetensors").is_file()
        assert (out / method / "metrics.csv").read_text().count("\n") >= 5
    report = (out / "report.md").read_text()
    for heading in ("Allocation", "Reviews and reputations", "Learning", "ROS 2 graph", "Gas used"):
        assert heading in report
    for png in ("learning_curves.png", "trajectory.png"):
        assert (out / png).read_bytes()[:8] == PNG_MAGIC
    assert set(summary["gas"]) >= {"addUser", "addModel", "allocateModels", "updateModelRep", "withdraw"}
