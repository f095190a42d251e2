"""`medc-bench train` runs end to end: the default learner on both sensing presets, the old baseline,
LeNet-5 and RS, with the speed-up ratios, ending with one JSON line (figures are measured, not asserted)."""

import json

from medc_training.cli.bench_train import REALISTIC, REALISTIC_40, main
from medc_training.config import CPU_SCALE, TrainConfig
from medc_training.envs import application


def test_bench_train_reports_the_default_learner_on_both_presets_and_its_ratio_to_maps(capsys) -> None:
    assert main(["--updates", "1", "--threads", "1", "--horizon", "128"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    result = json.loads(lines[-1])
    default = result["cpu_sparse"]
    app = application(TrainConfig().env)  # the default learner plays the default application's default
    assert default["observation"] == app.default_observation and default["arch"] == CPU_SCALE["arch"]
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


def test_bench_train_reports_each_default_learner_against_the_reference_estimator(capsys) -> None:
    """The A/B: each default learner (paper-simple 13x13, realistic 20x20 and 40x40) and its twin on the
    reference estimator, timed in the same run; --thread-ab adds the realistic ones on other threads."""
    assert main(["--updates", "1", "--threads", "1", "--horizon", "64", "--only-ab", "--thread-ab"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    result = json.loads(lines[-1])
    for m, grid in (("sparse", CPU_SCALE["grid"]), ("realistic_sparse", 20), ("realistic40_sparse", 40)):
        fused, reference = result[f"cpu_{m}"], result[f"cpu_{m}_reference"]
        assert (fused["estimator"], reference["estimator"]) == ("fused", "reference")
        assert fused["grid"] == reference["grid"] == grid
        ratio = fused["env_steps_per_s"] / reference["env_steps_per_s"]
        assert result[f"{m}_speedup_over_reference"] == ratio
    assert (result["cpu_realistic40_sparse"]["max_steps"], REALISTIC_40["grid"]) == (50, 40)
    assert result["cpu_realistic_sparse_2threads"]["threads"] == 2  # the run is on one
    assert "realistic_sparse_speedup_over_2threads" in result
    assert "cpu_rs" not in result and "cpu_baseline_maps_mlp" not in result  # --only-ab
    assert sum(line.startswith("A/B ") for line in lines) == 3 + 2


def test_bench_train_reports_the_kernel_split_over_threads_against_one_thread(capsys, monkeypatch) -> None:
    """The split's A/B: each default learner beside its twin with the native kernel on one thread, in the
    same run (here torch on one thread and the kernel on two); --no-split-ab drops the twins."""
    monkeypatch.setenv("MEDC_NATIVE_THREADS", "2")
    assert main(["--updates", "1", "--threads", "1", "--horizon", "64", "--only-ab", "--no-reference"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    result = json.loads(lines[-1])
    assert (result["torch_threads"], result["kernel_threads"]) == (1, 2) and len(result["load_average"]) == 3
    for m in ("sparse", "realistic_sparse", "realistic40_sparse"):
        split, one = result[f"cpu_{m}"], result[f"cpu_{m}_kernel1"]
        assert (split["kernel_threads"], one["kernel_threads"]) == (2, 1)
        assert split["threads"] == one["threads"] == 1 and split["grid"] == one["grid"]
        assert result[f"{m}_speedup_over_kernel1"] == split["env_steps_per_s"] / one["env_steps_per_s"]
    assert sum(line.startswith("A/B ") and "kernel on 2 threads / 1" in line for line in lines) == 3
    assert main(["--updates", "1", "--threads", "1", "--horizon", "64", "--only-ab", "--no-reference",
                 "--no-split-ab", "--no-realistic"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "cpu_sparse_kernel1" not in result and "sparse_speedup_over_kernel1" not in result
