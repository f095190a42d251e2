"""Saving and reloading policy bundles: same function, complete manifest, path or bytes."""

from __future__ import annotations

import hashlib
import json

import medc_training
import numpy as np
import pytest
import torch
from bundle_forge import MANIFEST
from medc_training.bundle import (
    FORMAT_VERSION,
    KNOWN_APPLICATIONS,
    BundleError,
    bundle_bytes,
    bundle_digest,
    load_bundle,
    read_manifest,
    save_bundle,
)
from medc_training.nets import make_actor_critic


@pytest.mark.parametrize("arch", ["lenet5", "mlp", "convnet-small"])
def test_reloaded_bundle_computes_identical_outputs(tmp_path, arch: str) -> None:
    torch.manual_seed(1)
    net = make_actor_critic(arch, (5, 10, 10), 8)
    path = save_bundle(tmp_path / f"{arch}.safetensors", net, MANIFEST)
    obs = torch.rand(9, 5, 10, 10)
    expected_logits, expected_value = net(obs)
    for source in (path, str(path), path.read_bytes(), bytearray(path.read_bytes())):
        bundle = load_bundle(source)
        logits, value = bundle.net(obs)
        assert torch.equal(logits, expected_logits) and torch.equal(value, expected_value)
        assert not bundle.net.training
        assert bundle.net.spec == net.spec
    assert list(tmp_path.iterdir()) == [path]  # the atomic write leaves no temporary file behind


def test_manifest_is_completed_from_the_net_and_the_application(tmp_path) -> None:
    net = make_actor_critic("lenet5", (5, 10, 10), 8)
    manifest = read_manifest(save_bundle(tmp_path / "b.safetensors", net, MANIFEST))
    assert manifest["format_version"] == FORMAT_VERSION
    assert manifest["application"] == "target_localization"
    assert manifest["environment"] == MANIFEST["environment"]
    assert manifest["observation"] == {
        "channels": 5, "height": 10, "width": 10,
        "channel_names": ["own_location", "team_locations", "readings", "visit_counts", "walls"],
        "name": "maps",
    }
    assert manifest["actions"] == ["N", "NE", "E", "SE", "S", "SW", "W", "NW"]
    assert manifest["architecture"] == net.spec
    assert manifest["training"]["method"] == "sparse" and manifest["training"]["seed"] == 7
    assert manifest["training"]["code_version"] == medc_training.__version__
    commit = manifest["training"]["git_commit"]
    assert commit is None or (len(commit) == 40 and int(commit, 16) >= 0)
    assert manifest["metrics"] == MANIFEST["metrics"]
    assert manifest["description"] == "test expert"


def test_unmeasured_metrics_are_stored_as_null() -> None:
    net = make_actor_critic("mlp", (5, 10, 10), 8)
    manifest = read_manifest(bundle_bytes(net, {**MANIFEST, "metrics": {"success_rate": float("nan"),
                                                                        "episode_length": 12.5}}))
    assert manifest["metrics"] == {"success_rate": None, "episode_length": 12.5}


def test_names_come_from_the_environment_module() -> None:
    from medc_training.envs import target_localization as tl

    manifest = read_manifest(bundle_bytes(make_actor_critic("mlp", (5, 10, 10), 8), MANIFEST))
    assert manifest["observation"]["channel_names"] == list(tl.CHANNELS)
    assert manifest["actions"] == list(tl.ACTION_NAMES)


def test_explicit_names_override_defaults_for_other_applications(tmp_path) -> None:
    net = make_actor_critic("mlp", (4, 10, 10), 5)
    manifest = {
        "application": "fleet_coordination", "environment": {"agents": 3, "customers": 8},
        "observation": {"channel_names": ["self", "team", "customers", "depots"]},
        "actions": ["stay", "N", "E", "S", "W"],
    }
    saved = read_manifest(save_bundle(tmp_path / "f.safetensors", net, manifest))
    assert saved["observation"]["channel_names"] == ["self", "team", "customers", "depots"]
    assert saved["actions"] == ["stay", "N", "E", "S", "W"]
    plain = read_manifest(bundle_bytes(make_actor_critic("mlp", (3, 10, 10), 4),
                                       {"application": "maze_cleaning"}))
    assert plain["observation"]["channel_names"] == ["channel_0", "channel_1", "channel_2"]
    assert plain["actions"] == ["action_0", "action_1", "action_2", "action_3"]


def test_policy_bundle_acts_only_on_allowed_moves() -> None:
    torch.manual_seed(3)
    bundle = load_bundle(bundle_bytes(make_actor_critic("lenet5", (5, 10, 10), 8), MANIFEST))
    obs = torch.rand(32, 5, 10, 10)
    mask = torch.rand(32, 8) < 0.4
    mask[torch.arange(32), torch.randint(0, 8, (32,))] = True
    probs = bundle.action_probs(obs, mask)
    assert torch.allclose(probs.sum(-1), torch.ones(32)) and float(probs[~mask].sum()) == 0.0
    greedy = bundle.act(obs, mask)
    assert greedy.dtype == torch.int64 and torch.equal(greedy, probs.argmax(-1))
    sampled = bundle.act(obs, mask, greedy=False, generator=torch.Generator().manual_seed(0))
    assert mask.gather(1, sampled[:, None]).all()
    # numpy inputs (what a ROS node holds) give the same answer
    assert torch.equal(bundle.act(obs.numpy(), mask.numpy()), greedy)
    unmasked = bundle.action_probs(obs)
    assert torch.allclose(unmasked, torch.softmax(bundle.net(obs)[0], -1))
    with pytest.raises(ValueError, match="mask must have shape"):
        bundle.action_probs(obs, mask[:, :4])


def test_bundle_moves_between_devices_without_changing_its_policy() -> None:
    bundle = load_bundle(bundle_bytes(make_actor_critic("mlp", (5, 10, 10), 8), MANIFEST))
    moved = bundle.to("cpu")
    obs = np.random.default_rng(0).random((4, 5, 10, 10), dtype=np.float32)
    assert torch.equal(moved.action_probs(obs), bundle.action_probs(obs))
    assert moved.sha256 == bundle.sha256 and moved.net is not bundle.net


def test_digest_is_the_sha256_of_the_file(tmp_path) -> None:
    path = save_bundle(tmp_path / "b.safetensors", make_actor_critic("mlp", (5, 10, 10), 8), MANIFEST)
    expected = hashlib.sha256(path.read_bytes()).hexdigest()
    assert bundle_digest(path) == expected == load_bundle(path).sha256
    assert bundle_digest(path.read_bytes()) == expected


def test_save_refuses_what_load_would_reject(tmp_path) -> None:
    net = make_actor_critic("lenet5", (5, 10, 10), 8)
    cases = [
        ({**MANIFEST, "application": "chess"}, "unknown application 'chess'"),
        ({**MANIFEST, "weights": "x"}, "unknown keys"),
        ({**MANIFEST, "environment": {"grid": 30}}, "environment.grid is 30"),
        ({**MANIFEST, "environment": {"walls": [1, 2]}}, "environment.walls must be"),
        ({**MANIFEST, "metrics": {"return": [1.0]}}, "metrics.return must be"),
        ({**MANIFEST, "metrics": {"return": np.float32(1.0)}}, "JSON values only"),
        ({**MANIFEST, "actions": ["N", "S"]}, "actions lists 2 names but the network has 8"),
    ]
    for manifest, message in cases:
        with pytest.raises(BundleError, match=message):
            save_bundle(tmp_path / "bad.safetensors", net, manifest)
    assert not list(tmp_path.iterdir())
    broken = make_actor_critic("mlp", (5, 10, 10), 8)
    with torch.no_grad():
        broken.policy.weight[0, 0] = float("inf")
    with pytest.raises(BundleError, match="non-finite"):
        bundle_bytes(broken, MANIFEST)


def test_manifest_is_stored_as_plain_json_any_safetensors_reader_sees(tmp_path) -> None:
    from safetensors import safe_open

    path = save_bundle(tmp_path / "b.safetensors", make_actor_critic("mlp", (5, 10, 10), 8), MANIFEST)
    with safe_open(str(path), framework="pt") as fh:
        stored = json.loads(fh.metadata()["medc.manifest"])
        assert set(fh.keys()) == set(make_actor_critic("mlp", (5, 10, 10), 8).state_dict())
    assert stored["application"] == "target_localization"


def test_bundle_of_a_real_environment_records_its_attributes() -> None:
    from medc_training.envs import ENV_NAMES, make_batched

    env = make_batched("target_localization", num_envs=2, seed=0, agents=2, walls=1, grid=10)
    net = make_actor_critic("lenet5", env.obs_shape, env.num_actions)
    from medc_training.runner import observation_section

    manifest = {"application": env.name, "environment": env.attributes, **observation_section(env)}
    bundle = load_bundle(bundle_bytes(net, manifest))
    assert bundle.observation == env.observation.name
    assert bundle.manifest["environment"] == env.attributes
    obs, mask = env.reset(seed=1)
    actions = bundle.act(obs.flatten(0, 1), mask.flatten(0, 1))
    assert mask.flatten(0, 1).gather(1, actions[:, None]).all()
    assert tuple(ENV_NAMES) == KNOWN_APPLICATIONS


def test_same_policy_and_manifest_give_the_same_bytes() -> None:
    # One policy, one CID: re-publishing an unchanged model must not create a new registry entry.
    net = make_actor_critic("lenet5", (5, 10, 10), 8)
    manifest = {**MANIFEST, "training": {**MANIFEST["training"], "git_commit": None}}
    first = bundle_bytes(net, manifest)
    assert bundle_bytes(net, manifest) == first
    reloaded = load_bundle(first)
    assert bundle_bytes(reloaded.net, {k: v for k, v in reloaded.manifest.items()
                                       if k not in ("format", "format_version", "architecture")}) == first


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600)])
def test_saved_bundle_has_the_mode_open_would_give_it(tmp_path, umask: int, mode: int) -> None:
    import os
    import stat

    net = make_actor_critic("mlp", (5, 10, 10), 8)
    old = os.umask(umask)
    try:
        path = save_bundle(tmp_path / "shared.safetensors", net, MANIFEST)
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == mode  # not mkstemp's 0600 whatever the umask
