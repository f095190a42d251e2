"""`medc-bench train` runs end to end: the default learner, the old baseline, LeNet-5 and RS, with the
speed-up ratio, ending with one JSON line (figures are measured, not asserted)."""

import json

from medc_training.cli.bench_train import main
from medc_training.config import CPU_SCALE, TrainConfig


def test_bench_train_reports_the_default_learner_and_its_ratio_to_the_baseline(capsys) -> None:
    assert main(["--updates", "1", "--threads", "1"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    result = json.loads(lines[-1])
    default = result["cpu_sparse"]
    assert default["observation"] == TrainConfig().observation and default["arch"] == CPU_SCALE["arch"]
    assert result["cpu_baseline_maps_mlp"]["observation"] == "maps"
    assert result["cpu_lenet5"]["arch"] == "lenet5"
    assert result["speedup_over_baseline"] == default["env_steps_per_s"] / result[
        "cpu_baseline_maps_mlp"]["env_steps_per_s"]
    assert any(line.startswith("default learner / baseline") for line in lines)
