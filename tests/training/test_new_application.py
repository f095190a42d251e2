"""A fourth application is one core and one descriptor: medc-train (its config and a short run),
the bundle manifest, the report and the plan take it without a change of theirs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from medc_training.bundle import (
    BundleError,
    complete_manifest,
    load_bundle,
    manifest_observation,
    save_bundle,
)
from medc_training.cli.train import build_parser, config_from_args
from medc_training.envs import APPLICATIONS, Application, make_batched, register, unregister
from medc_training.envs.core import MapsObservationEnv, check_bool, check_core_options, maps_channels
from medc_training.envs.grid import ACTIONS, action_deltas, neighbour_index, pad_blocked, random_free_cells
from medc_training.nets import make_actor_critic
from medc_training.runner import observation_section

TOY = "beacon_search"


def _cli(*args: str):
    """The TrainConfig ``medc-train ARGS --out run`` builds."""
    return config_from_args(build_parser().parse_args([*args, "--out", "run"]))


class BeaconSearch(MapsObservationEnv):
    """A team finds one beacon on an open grid; the oracle steps towards it."""

    name = TOY
    CHANNELS = ("own_location", "team_locations", "beacon")

    def __init__(self, num_envs: int = 1, device: str | torch.device = "cpu", seed: int | None = None,
                 agents: int = 2, grid: int = 6, max_steps: int = 20, copy_obs: bool = True,
                 observation: str = "maps") -> None:
        self.grid, self.num_agents, self.max_steps = check_core_options(
            grid, agents, max_steps, grid_range=(3, 16), max_agents=lambda g: 4)
        self.copy_obs = check_bool("copy_obs", copy_obs)
        super().__init__(num_envs, device, seed)
        self.num_actions = len(ACTIONS)
        self._set_observation(observation, len(self.CHANNELS))
        self._deltas = action_deltas(self.device)
        self._started = False

    @property
    def attributes(self) -> dict[str, Any]:
        return {"agents": self.num_agents, "grid": self.grid, "max_steps": self.max_steps}

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        k = self.num_envs if rows is None else len(rows)
        free = torch.ones(k, self.grid, self.grid, dtype=torch.bool, device=self.device)
        positions = random_free_cells(free, self.num_agents, self.generator)
        beacon = random_free_cells(free, 1, self.generator)[:, 0]
        if rows is None:
            self.positions, self.beacon = positions, beacon
            self.blocked_pad = pad_blocked(~free)
            self.t = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        else:
            self.positions[rows], self.beacon[rows], self.t[rows] = positions, beacon, 0

    def _observe_maps(self) -> torch.Tensor:
        b, n, g = self.num_envs, self.num_agents, self.grid
        out = torch.zeros(b, n, len(self.CHANNELS), g * g, device=self.device)
        cell = self.positions[..., 0] * g + self.positions[..., 1]  # [B,N]
        out[:, :, 0].scatter_(2, cell.unsqueeze(2), 1.0)
        out[:, :, 1] = out[:, :, 0].sum(1, keepdim=True).clamp(max=1.0)
        beacon = (self.beacon[:, 0] * g + self.beacon[:, 1]).view(b, 1, 1).expand(b, n, 1)
        out[:, :, 2].scatter_(2, beacon, 1.0)
        return out.view(b, n, len(self.CHANNELS), g, g)

    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        success = (self.positions == self.beacon.unsqueeze(1)).all(-1).any(1)
        return success.float() - 0.1, success

    def oracle_action_scores(self) -> torch.Tensor:
        b, n = self.positions.shape[:2]
        idx = neighbour_index(self.positions, self.grid, self._deltas).view(b, -1)
        rows, cols = (idx // (self.grid + 2)) - 1, (idx % (self.grid + 2)) - 1
        dist = torch.maximum((rows - self.beacon[:, :1]).abs(), (cols - self.beacon[:, 1:]).abs())
        return torch.where(self.mask, -dist.view(b, n, -1).float(), float("-inf"))


@pytest.fixture
def toy():
    app = register(Application(name=TOY, core=BeaconSearch, default_observation="maps",
                               channels=maps_channels(BeaconSearch.CHANNELS)))
    yield app
    unregister(TOY)
    assert TOY not in APPLICATIONS


def test_medc_train_builds_the_config_of_a_new_application(toy):
    cfg = _cli("--env", TOY, "--agents", "2", "--grid", "6", "--observation", "ego2").validate()
    assert (cfg.env, cfg.observation, cfg.env_options) == (TOY, "ego2", {"observation": "ego2"})
    assert cfg.make_options() == {"observation": "ego2", "agents": 2, "grid": 6, "max_steps": cfg.max_steps}
    assert cfg.env_attributes() == {"agents": 2, "grid": 6, "max_steps": cfg.max_steps, "observation": "ego2"}
    env = make_batched(TOY, num_envs=3, seed=0, **cfg.make_options())
    assert env.obs_shape == (3, 5, 5) and env.observation_channels == ("off_grid", "team_locations", "beacon")
    obs, mask = env.reset(seed=1)
    out = env.step(env.oracle_action_scores().argmax(-1))
    assert obs.shape == (3, 2, 3, 5, 5) and mask.shape == (3, 2, 8) and out.reward.shape == (3,)
    # Without --observation it takes its own default, whatever the scale names.
    plain = _cli("--env", TOY)
    assert make_batched(TOY, **plain.make_options()).observation_name == toy.default_observation
    with pytest.raises(ValueError, match="has no source estimate"):
        cfg = _cli("--env", TOY, "--observation", "ego2+estimate")
        make_batched(TOY, **cfg.make_options())
    with pytest.raises(ValueError, match="unknown option"):
        make_batched(TOY, walls=2)


def test_a_new_applications_bundle_passes_the_manifest_check(toy, tmp_path):
    env = make_batched(TOY, num_envs=1, grid=6, observation="ego2")
    net = make_actor_critic("mlp", env.obs_shape, env.num_actions)
    manifest = {"application": TOY, "environment": env.attributes, **observation_section(env),
                "training": {"method": "dagger"}}
    full = complete_manifest(net, manifest)
    assert full["observation"]["channel_names"] == list(env.observation_channels)
    assert manifest_observation(full) == "ego2"
    bundle = load_bundle(save_bundle(tmp_path / "toy.safetensors", net, manifest))
    assert bundle.manifest["application"] == TOY and bundle.observation == "ego2"
    with pytest.raises(BundleError, match="'ego3' is 7x7 here"):
        complete_manifest(net, {**manifest, "observation": {"name": "ego3"}})
    for view in ("ego2+estimate", "ego2+posterior"):
        with pytest.raises(BundleError, match="not a view beacon_search takes"):
            complete_manifest(net, {**manifest, "observation": {"name": view}})
    maps = make_batched(TOY, grid=6)
    assert observation_section(maps) == {}  # 'maps' is not recorded; the manifest reads as maps
    plain = complete_manifest(make_actor_critic("mlp", maps.obs_shape, 8), {"application": TOY,
                                                                             "environment": maps.attributes})
    assert plain["observation"]["channel_names"] == list(BeaconSearch.CHANNELS)
    assert manifest_observation(plain) is None
    unregister(TOY)
    try:
        with pytest.raises(BundleError, match="unknown application"):
            load_bundle(tmp_path / "toy.safetensors")
    finally:
        register(toy)


def test_the_report_and_the_plan_take_a_new_application(toy, tmp_path):
    from medc_lab.plan import Plan
    from medc_lab.report.markdown import expert_table
    from medc_lab.report.reference_play import controllers_refuse
    from medc_training.config import TrainConfig

    cfg = TrainConfig(env=TOY, agents=2, grid=6, eval_episodes=8)
    assert cfg.observation is None and cfg.make_options() == {"agents": 2, "grid": 6, "max_steps": 100}
    assert "keeps none" in controllers_refuse(cfg)
    models = tmp_path / "models"
    plan = Plan("cpu", 1, tmp_path / "out", models)
    job = plan._expert_job("beacon-A2", TOY, 2, "mlp", 64, False, env_options={"observation": "ego2"},
                           max_steps=20, grid=6, greedy=False)
    assert job["config"]["env"] == TOY and job["config"]["env_options"] == {"observation": "ego2"}
    env = make_batched(TOY, grid=6, max_steps=20, observation="ego2")
    net = make_actor_critic("mlp", env.obs_shape, env.num_actions)
    (models / "experts").mkdir(parents=True)
    save_bundle(models / "experts" / "beacon-A2.safetensors", net, {
        "application": TOY, "environment": env.attributes, **observation_section(env),
        "training": {"method": "dagger", "steps": 64, "arch": "mlp"},
        "metrics": {f"{how}_{what}": value for how in ("greedy", "sampled", "random")
                    for what, value in (("episode_length", 7.5), ("success_rate", 1.0))}})
    # An equal DAgger bundle is reused; one for another grid is retrained.
    again = {"name": "beacon-A2", "env": TOY, "agents": 2, "arch": "mlp", "steps": 64, "retrain": False,
             "env_options": {"observation": "ego2"}, "max_steps": 20}
    assert plan._expert_job(**again, grid=6) is None
    assert plan._expert_job(**again, grid=7) is not None
    assert "experts/beacon-A2 | mlp | dagger 64" in expert_table(models)
    assert Path(job["bundle_to"]).name == "beacon-A2.safetensors"


def test_medc_train_trains_it_and_the_report_reads_the_run(toy, tmp_path):
    from medc_lab.report.finder import load_curves
    from medc_lab.report.reference_play import random_play
    from medc_training.cli.train import main as train_main

    out = tmp_path / "runs" / "beacon" / "seed0"
    assert train_main(["--env", TOY, "--agents", "2", "--grid", "6", "--max-steps", "12",
                       "--observation", "ego2", "--num-envs", "4", "--horizon", "32", "--epochs", "1",
                       "--eval-every", "64", "--eval-episodes", "4", "--eval-envs", "4", "--arch", "mlp",
                       "--steps", "128", "--no-tensorboard", "--quiet", "--out", str(out)]) == 0
    bundle = load_bundle(out / "policy.safetensors")  # the manifest check
    assert bundle.manifest["application"] == TOY and bundle.observation == "ego2"
    assert bundle.manifest["observation"]["channel_names"] == ["off_grid", "team_locations", "beacon"]
    steps, curves, summaries = load_curves(tmp_path, "beacon")
    assert steps and len(curves) == 1 and len(curves[0]) == len(steps)
    assert all(1 <= length <= 12 for length in curves[0])
    assert summaries[0]["config"]["env"] == TOY
    reference = random_play(tmp_path, summaries[0]["config"])
    assert 1 <= reference["episode_length"] <= 12 and 0 <= reference["success_rate"] <= 1
    assert (tmp_path / "random_play.json").exists()
