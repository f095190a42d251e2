"""`medc-bench env` runs end to end and ends with one JSON line (figures are not asserted)."""

from __future__ import annotations

import json

from medc_training.envs.bench import main


def test_bench_prints_figures_and_ends_with_json(capsys) -> None:
    rc = main(
        [
            "--num-envs",
            "4",
            "--grid",
            "10",
            "--steps",
            "5",
            "--warmup",
            "2",
            "--one-by-one-steps",
            "2",
            "--rounds",
            "3",
        ]
    )
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    figures = json.loads(lines[-1])
    assert {"batched_agent_steps_per_s", "one_by_one_agent_steps_per_s", "ratio"} <= set(figures)
    assert figures["batched_agent_steps_per_s"] > 0 and figures["one_by_one_agent_steps_per_s"] > 0
    assert sum(line.startswith("round ") for line in lines) == 3
