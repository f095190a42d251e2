"""medc-bench ros's measuring loop works (figures are checked by the benchmark, not here)."""

from __future__ import annotations

import pytest


@pytest.mark.timing
@pytest.mark.ros
@pytest.mark.parametrize("in_process", [True, False])
def test_bench_measures_team_decision_latency(rclpy_context, bundles, in_process):
    from medc_bringup.bench_ros import run_graph

    r = run_graph(3, bundles["a"], in_process=in_process, steps=30, warmup=5, grid=10, walls=1)
    assert r["steps"] >= 30 and r["deployment"] == ("in-process" if in_process else "processes")
    assert 0 < r["latency_ms_p50"] <= r["latency_ms_p99"]
    assert r["team_steps_per_s"] > 0 and r["dropped"] == 0
