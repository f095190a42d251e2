"""Policy bundles of different architectures advise one MEDC run; mismatched experts are refused."""

import json

import pytest
import torch
from medc_training.bundle import load_bundle, save_bundle
from medc_training.cli.train import main as train_main
from medc_training.config import TrainConfig
from medc_training.envs.tl_observation import DEFAULT_OBSERVATION, observation_shape
from medc_training.experts import BundleExpert, ExpertError
from medc_training.medc import expert_scores_for
from medc_training.nets import make_actor_critic
from medc_training.ppo import Trainer

TINY = dict(env="target_localization", agents=2, walls=0, grid=6, max_steps=12, num_envs=4, horizon=32,
            epochs=1, minibatches=2, eval_every=32, eval_steps=16, eval_envs=4, eval_episodes=4, seed=0)


def _bundle(tmp_path, arch, grid=6, agents=1, observation=DEFAULT_OBSERVATION):
    torch.manual_seed(len(arch))
    net = make_actor_critic(arch, observation_shape(observation, grid), 8)
    path = tmp_path / f"{arch}-{grid}-{observation}.safetensors"
    save_bundle(path, net, {"application": "target_localization", "observation": {"name": observation},
                            "environment": {"agents": agents, "walls": 0, "grid": grid}})
    return path


def test_two_architectures_score_their_own_rows(tmp_path):
    experts = [BundleExpert(load_bundle(_bundle(tmp_path, "lenet5"))),
               BundleExpert(load_bundle(_bundle(tmp_path, "mlp")))]
    obs = torch.rand(4, *experts[0].obs_shape)
    mask = torch.ones(4, 8, dtype=torch.bool)
    scores = expert_scores_for(experts, torch.tensor([0, 1, 1, 0]), obs, mask, torch.arange(4))
    for row, e in enumerate([0, 1, 1, 0]):
        own = torch.log(experts[e].bundle.action_probs(obs[row:row + 1], mask[row:row + 1]))
        assert torch.allclose(scores[row], own[0], atol=1e-5)


def test_medc_run_with_lenet5_and_mlp_experts_follows_them(tmp_path):
    experts = [BundleExpert(load_bundle(_bundle(tmp_path, "lenet5"))),
               BundleExpert(load_bundle(_bundle(tmp_path, "mlp")))]
    cfg = TrainConfig(method="medc", expert_rate=1.0, total_steps=32, **TINY)
    trainer = Trainer(cfg, experts)
    trainer.collect()
    stats = trainer.take_train_stats()
    # A fresh policy is near-uniform (every P >= Q), so each suggestion passes the Q test.
    assert stats["expert_follow_rate"] == 1.0
    assert stats["expert_step_fraction"] == 1.0


def test_expert_from_another_grid_is_rejected_where_the_observation_depends_on_the_grid(tmp_path):
    wrong = BundleExpert(load_bundle(_bundle(tmp_path, "lenet5", grid=8, observation="maps")))
    cfg = TrainConfig(method="medc", total_steps=32, **{**TINY, "observation": "maps"})
    with pytest.raises(ExpertError, match="same grid size"):
        Trainer(cfg, [wrong])
    # An agent-centred window has the same shape on every grid: that expert can advise here.
    ego = BundleExpert(load_bundle(_bundle(tmp_path, "lenet5", grid=8, observation="ego3+estimate")))
    Trainer(TrainConfig(method="medc", total_steps=32, **{**TINY, "observation": "ego3+estimate"}), [ego])


def test_expert_taking_another_observation_is_rejected(tmp_path):
    maps = BundleExpert(load_bundle(_bundle(tmp_path, "mlp", observation="maps")))
    with pytest.raises(ExpertError, match="takes the observation 'maps', but this environment produces"):
        Trainer(TrainConfig(method="medc", total_steps=32, **TINY), [maps])


def test_medc_needs_an_expert():
    with pytest.raises(ValueError, match="at least one expert"):
        Trainer(TrainConfig(method="medc", total_steps=32, **TINY))


def test_cli_medc_with_two_architectures_writes_bundle_csv_and_curve(tmp_path, capsys):
    a, b = _bundle(tmp_path, "lenet5"), _bundle(tmp_path, "convnet-small")
    out = tmp_path / "run"
    code = train_main(["--agents", "2", "--walls", "0", "--grid", "6", "--max-steps", "12", "--num-envs", "4",
                       "--horizon", "32", "--epochs", "1", "--eval-every", "32", "--eval-steps", "16",
                       "--steps", "64", "--method", "medc", "--expert", str(a), "--expert", str(b),
                       "--expert", "random", "--expert", f"malicious:{a}", "--out", str(out), "--quiet"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["steps"] == 64
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    for column in ("step", "episode_length", "success_rate", "expert_follow_rate", "policy_loss", "sps"):
        assert column in header
    assert list((out / "tb").glob("events.out.tfevents.*"))
    assert (out / "learning_curve.png").stat().st_size > 1000
    manifest = load_bundle(out / "policy.safetensors").manifest
    assert manifest["training"]["method"] == "medc" and manifest["environment"]["agents"] == 2


def test_cli_rejects_bad_input_with_a_clear_message(tmp_path, capsys):
    assert train_main(["--method", "medc", "--expert", "nope.safetensors", "--out", str(tmp_path)]) == 2
    assert "neither a bundle file" in capsys.readouterr().err
    assert train_main(["--method", "frl", "--frl-users", "A1X0", "--out", str(tmp_path)]) == 2
    assert "AyWz" in capsys.readouterr().err
