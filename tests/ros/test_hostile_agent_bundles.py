"""At the agent, a manifest's grid is bounded before the agent
allocates anything (the process exits with the reason, no traceback), denormal bundles run
flushed, and the agent's policy cache evicts. Each test builds its hostile bundle itself."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import weakref
from pathlib import Path

import pytest
import torch
from conftest import make_bundle

BIN = Path(sys.executable).parent


def _ego_bundle(path: Path, grid) -> Path:
    """A valid-looking target-localization bundle on an agent-centred 9x9 window (its input does
    not depend on the grid) whose manifest names ``grid``: written by hand, past save_bundle."""
    from medc_training.bundle import MANIFEST_KEY, bundle_bytes
    from medc_training.envs.tl_observation import observation_shape, parse_observation
    from medc_training.nets import make_actor_critic
    from safetensors.torch import save as st_save

    spec = parse_observation("ego4")
    torch.manual_seed(0)
    net = make_actor_critic("lenet5", observation_shape(spec, 10), 8)
    good = bundle_bytes(net, {"application": "target_localization", "observation": {"name": "ego4"},
                              "environment": {"grid": 10, "agents": 3}})
    n = int.from_bytes(good[:8], "little")
    manifest = json.loads(json.loads(good[8:8 + n])["__metadata__"][MANIFEST_KEY])
    manifest["environment"]["grid"] = grid
    path.write_bytes(st_save(dict(net.state_dict()), metadata={MANIFEST_KEY: json.dumps(manifest)}))
    return path


@pytest.mark.parametrize("grid", [10**6, 256])
def test_an_agent_refuses_a_manifest_grid_beyond_the_bound_before_allocating(grid, tmp_path) -> None:
    from medc_agents.node import scenario_from_bundle
    from medc_agents.policy_slot import PolicyRejected
    from medc_training.bundle import MAX_BUNDLE_GRID

    path = _ego_bundle(tmp_path / "grid.safetensors", grid)
    with pytest.raises(PolicyRejected, match=rf"environment.grid is {grid}.*from 1 to {MAX_BUNDLE_GRID}"):
        scenario_from_bundle(str(path), 0, 0, "")
    # Given as a parameter, the same bound.
    with pytest.raises(PolicyRejected, match=f"grid {grid} is over the {MAX_BUNDLE_GRID}"):
        scenario_from_bundle("greedy", 3, grid, "")
    assert scenario_from_bundle(str(_ego_bundle(tmp_path / "ok.safetensors", 30)), 0, 0, "")[:2] == (3, 30)


@pytest.mark.timing
@pytest.mark.ros
def test_the_agent_process_exits_with_the_reason_not_a_traceback(tmp_path) -> None:
    path = _ego_bundle(tmp_path / "huge.safetensors", 10**6)
    proc = subprocess.run(
        [str(BIN / "medc-agent"), "--ros-args", "-p", "agent_id:=agent_0", "-p", f"policy:={path}"],
        capture_output=True, text=True, timeout=120, env=os.environ.copy())
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-3000:]
    assert "environment.grid is 1000000" in out and "from 1 to 64" in out
    assert "Traceback" not in out and "RuntimeError" not in out


def test_the_agents_policy_cache_evicts(tmp_path, monkeypatch) -> None:
    from medc_agents import policy_slot as policy_mod
    from medc_agents.policy_slot import PolicySlot

    policy_mod._LOADED.clear()
    slot = PolicySlot((5, 10, 10), 8)
    refs = []
    for i in range(3 * policy_mod.MAX_CACHED_POLICIES):  # distinct bundles, swapped in one by one
        path = make_bundle(tmp_path / f"p{i}.safetensors", 100 + i)
        refs.append(weakref.ref(slot.swap(str(path)).bundle))
        assert len(policy_mod._LOADED) <= policy_mod.MAX_CACHED_POLICIES
    gc.collect()
    alive = [r() is not None for r in refs]
    # The running one and the few most recent are kept; every older one is freed.
    assert alive[-1] and sum(alive) <= policy_mod.MAX_CACHED_POLICIES, alive
    assert not any(alive[:-policy_mod.MAX_CACHED_POLICIES])
    # A bound in bytes too: with room for one bundle's weights, only the latest stays.
    monkeypatch.setattr(policy_mod, "MAX_CACHED_POLICY_BYTES", 1)
    slot.swap(str(tmp_path / "p0.safetensors"))
    assert len(policy_mod._LOADED) == 1
    # Swapping back to a bundle still cached costs no reload: the same object.
    monkeypatch.setattr(policy_mod, "MAX_CACHED_POLICY_BYTES", 64 << 20)
    first = slot.swap(str(tmp_path / "p1.safetensors")).bundle
    slot.swap(str(tmp_path / "p2.safetensors"))
    assert slot.swap(str(tmp_path / "p1.safetensors")).bundle is first
    policy_mod._LOADED.clear()


def test_a_denormal_bundle_runs_at_the_agent_with_zero_weights_and_flushed_arithmetic(tmp_path) -> None:
    from medc_agents.policy_slot import PolicySlot
    path = make_bundle(tmp_path / "den.safetensors", 7)
    from medc_training.bundle import MANIFEST_KEY
    from safetensors.torch import load_file
    from safetensors.torch import save as st_save

    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    meta = json.loads(data[8:8 + n])["__metadata__"]
    tensors = {k: (torch.where(v >= 0, 1e-40, -1e-40) if v.dim() == 4 else v)
               for k, v in load_file(str(path)).items()}
    path.write_bytes(st_save(tensors, metadata={MANIFEST_KEY: meta[MANIFEST_KEY]}))
    slot = PolicySlot((5, 10, 10), 8)
    loaded = slot.swap(str(path))
    assert all((p == 0).all() for p in loaded.bundle.net.parameters() if p.dim() == 4)
    action = slot.act(torch.rand(5, 10, 10), torch.ones(8, dtype=torch.bool))
    assert 0 <= action < 8


class _Store:
    """Serves fixed bytes for any CID (the content hash is the content store's business)."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files

    def fetch(self, cid: str) -> bytes:
        return self.files[cid]


@pytest.mark.ros
def test_the_bridge_refuses_a_huge_grid_and_remembers_a_refused_content(tmp_path, monkeypatch) -> None:
    """Items 4 and 6 at the registry bridge (load_untrusted, as the agent): the grid bound, and a
    refusal after the header checks remembered by content, so the same bytes under another CID
    are refused without loading them again (the slow-bundle case: tests/bundle)."""
    from medc_registry.bridge_node import BridgeError, RegistryBridge
    from medc_training.bundle import MANIFEST_KEY
    from medc_training.bundle import policy as policy_mod
    from safetensors.torch import load_file
    from safetensors.torch import save as st_save

    good = make_bundle(tmp_path / "good.safetensors", 9, grid=30)
    data = good.read_bytes()
    meta = json.loads(data[8:8 + int.from_bytes(data[:8], "little")])["__metadata__"]
    tensors = load_file(str(good))
    tensors["policy.bias"][0] = float("nan")
    broken = st_save(tensors, metadata={MANIFEST_KEY: meta[MANIFEST_KEY]})
    files = {"huge": _ego_bundle(tmp_path / "huge.safetensors", 10**6).read_bytes(),
             "nan": broken, "nan-again": broken}
    bridge = RegistryBridge(_Store(files), tmp_path / "cache")
    with pytest.raises(BridgeError, match=r"environment.grid is 1000000.*from 1 to 64"):
        bridge.fetch("huge")
    with pytest.raises(BridgeError, match="NaN or infinite") as first:
        bridge.fetch("nan")
    assert "refused before" not in str(first.value)
    loaded = []  # every bundle decoded past its header (then dry-run), from here on
    real_load = policy_mod._load
    monkeypatch.setattr(policy_mod, "_load", lambda *args: loaded.append(args) or real_load(*args))
    with pytest.raises(BridgeError, match=r"NaN or infinite .*refused before; not checked again"):
        bridge.fetch("nan-again")
    assert loaded == []  # refused by its content's digest, without loading it again
    assert list((tmp_path / "cache").iterdir()) == []
