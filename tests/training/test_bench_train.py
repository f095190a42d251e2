"""`medc-bench train` runs end to end: the default learner on both sensing presets, the old baseline,
LeNet-5 and RS, with the speed-up ratios, ending with one JSON line (figures are measured, not asserted)."""

import json

from medc_training.cli.bench_train import REALISTIC, main
from medc_training.config import CPU_SCALE, TrainConfig


def test_bench_train_reports_the_default_learner_on_both_presets_and_its_ratio_to_maps(capsys) -> None:
    assert main(["--updates", "1", "--threads", "1", "--horizon", "128"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    result = json.loads(lines[-1])
    default = result["cpu_sparse"]
    assert default["observation"] == TrainConfig().observation and default["arch"] == CPU_SCALE["arch"]
    assert (default["sensing"], default["grid"], default["max_steps"]) == (
        "paper-simple", CPU_SCALE["grid"], CPU_SCALE["max_steps"])
    assert result["cpu_baseline_maps_mlp"]["observation"] == "maps"
    assert result["cpu_lenet5"]["arch"] == "lenet5"
    assert result["speedup_over_baseline"] == default["env_steps_per_s"] / result[
        "cpu_baseline_maps_mlp"]["env_steps_per_s"]
    realistic, maps = result["cpu_realistic_sparse"], result["cpu_realistic_baseline_maps_mlp"]
    assert (realistic["sensing"], realistic["grid"], realistic["max_steps"]) == ("realistic", 20, 100)
    assert default["horizon"] == realistic["horizon"] == 128
    assert realistic["observation"] == default["observation"] and realistic["arch"] == default["arch"]
    assert (maps["sensing"], maps["observation"]) == ("realistic", "maps")
    assert result["realistic_speedup_over_baseline"] == realistic["env_steps_per_s"] / maps["env_steps_per_s"]
    assert result["realistic_over_simple"] == realistic["env_steps_per_s"] / default["env_steps_per_s"]
    assert REALISTIC["env_options"] == {"sensing": "realistic"}  # the learners did not change it
    assert any(line.startswith("default learner / baseline") for line in lines)
    assert any(line.startswith("realistic: default learner / baseline") for line in lines)
