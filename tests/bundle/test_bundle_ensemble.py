"""Several bundles played as one policy: mean probabilities, members that must agree."""

from __future__ import annotations

import pytest
import torch
from bundle_forge import MANIFEST
from medc_training.bundle import BundleError, load_bundle, save_bundle
from medc_training.bundle.ensemble import MAX_MEMBERS, ensemble, load_ensemble
from medc_training.nets import make_actor_critic


def _saved(tmp_path, name: str, seed: int, shape=(5, 10, 10), manifest=MANIFEST):
    torch.manual_seed(seed)
    return save_bundle(tmp_path / f"{name}.safetensors", make_actor_critic("mlp", shape, 8), manifest)


def test_the_ensemble_plays_the_members_mean_probabilities(tmp_path):
    paths = [_saved(tmp_path, f"m{k}", seed=k) for k in range(3)]
    members = [load_bundle(p) for p in paths]
    one = load_ensemble(paths)
    obs = torch.rand(16, 5, 10, 10)
    logits, value = one.net(obs)
    with torch.no_grad():
        outs = [b.net(obs) for b in members]
    mean = torch.stack([torch.softmax(lg, -1) for lg, _ in outs]).mean(0)
    assert torch.allclose(torch.softmax(logits, -1), mean, atol=1e-6)
    assert torch.allclose(value, torch.stack([v for _, v in outs]).mean(0), atol=1e-6)
    assert one.obs_shape == members[0].obs_shape and one.manifest["ensemble"] == [b.sha256 for b in members]
    # Where the members disagree the ensemble can take a move no single member takes first.
    assert (logits.argmax(-1) != outs[0][0].argmax(-1)).any()


def test_an_ensemble_of_one_policy_twice_moves_as_that_policy(tmp_path):
    path = _saved(tmp_path, "m", seed=0)
    obs = torch.rand(32, 5, 10, 10)
    with torch.no_grad():
        alone = load_bundle(path).net(obs)[0].argmax(-1)
    assert torch.equal(load_ensemble([path, path]).net(obs)[0].argmax(-1), alone)


def test_members_that_disagree_or_too_many_are_refused(tmp_path):
    a = _saved(tmp_path, "a", seed=0)
    grid12 = {**MANIFEST, "environment": {**MANIFEST["environment"], "grid": 12}}
    other_shape = _saved(tmp_path, "b", seed=1, shape=(5, 12, 12), manifest=grid12)
    with pytest.raises(BundleError, match="observation shape"):
        load_ensemble([a, other_shape])
    with pytest.raises(BundleError, match="2 to"):
        load_ensemble([a])
    with pytest.raises(BundleError, match="2 to"):
        ensemble([load_bundle(a)] * (MAX_MEMBERS + 1))
