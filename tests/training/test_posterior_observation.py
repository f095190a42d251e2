"""A team trained on the source-posterior view (``ego6+estimate+posterior``) in the benchmark's world:
``medc-train`` makes a bundle that names the view, ``medc-radbench`` plays it, and an environment that
makes another view refuses it."""

from __future__ import annotations

import json

import pytest
from medc_training.bundle import load_bundle, read_manifest
from medc_training.cli.radbench import main as radbench_main
from medc_training.cli.train import main as train_main
from medc_training.config import TrainConfig
from medc_training.experts import BundleExpert, ExpertError
from medc_training.ppo import Trainer
from medc_training.runner import BUNDLE

VIEW = "ego6+estimate+posterior"
TRAIN_ARGS = ["--world", "radbench", "--observation", VIEW, "--agents", "3", "--walls", "2", "--grid", "20",
              "--max-steps", "40", "--num-envs", "4", "--horizon", "16", "--epochs", "1",
              "--eval-every", "64", "--eval-episodes", "2", "--eval-envs", "2", "--env-option", "pool=12",
              "--arch", "mlp", "--steps", "64", "--quiet", "--no-tensorboard", "--threads", "1"]


pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_team_trained_on_the_posterior_view_plays_the_benchmark(tmp_path, capsys):
    out = tmp_path / "run"
    assert train_main([*TRAIN_ARGS, "--out", str(out)]) == 0
    path = out / BUNDLE
    manifest = read_manifest(path)
    assert manifest["observation"]["name"] == VIEW
    assert manifest["observation"]["channel_names"][-2:] == ["source_estimate", "source_posterior"]
    assert manifest["environment"]["world"] == "radbench"
    bundle = load_bundle(path)
    assert bundle.observation == VIEW and tuple(bundle.obs_shape) == (6, 13, 13)
    capsys.readouterr()
    assert radbench_main([str(path), "greedy", "--grid", "20", "--agents", "3", "--obstructions", "2",
                          "--snr", "medium", "--episodes", "3", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["reference"] == str(path)
    (row,) = result["sets"].values()
    assert row["policies"][str(path)]["episodes"] == 3
    # An environment that shows the estimate alone refuses it as an expert, naming both views.
    tiny = dict(env="target_localization", agents=2, walls=0, grid=7, max_steps=12, num_envs=2, horizon=8,
                epochs=1, minibatches=1, eval_envs=2, eval_episodes=2, total_steps=16, arch="mlp",
                observation="ego6+estimate", env_options={"sensing": "realistic"})
    with pytest.raises(ExpertError, match=r"takes the observation 'ego6\+estimate\+posterior', but this "
                                          r"environment produces 'ego6\+estimate'"):
        Trainer(TrainConfig(method="medc", **tiny), [BundleExpert(bundle)])
