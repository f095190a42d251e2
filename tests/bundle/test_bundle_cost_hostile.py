"""A bundle's cost is bounded by construction and measured on real
data, a slow bundle is refused after about the limit and remembered, and the grid a manifest
names is bounded before anything is sized from it. Each test builds its hostile file itself."""

from __future__ import annotations

import shutil
import time

import pytest
import torch
from bundle_forge import bomb_spec, conv, forge, spec_parts, valid_parts
from medc_training.bundle import (
    MAX_BUNDLE_AGENTS,
    MAX_BUNDLE_GRID,
    BundleError,
    dry_run_observations,
    flush_denormals,
    load_bundle,
    load_untrusted,
    read_manifest,
)
from medc_training.bundle import dryrun as dryrun_mod
from medc_training.bundle import policy as policy_mod
from medc_training.cli.inspect import main as inspect_main

TINY = torch.finfo(torch.float32).tiny


def _subnormal_bundle(arch: str = "convnet-small", grid: int = 30) -> bytes:
    """A valid bundle whose convolution weights are all float32 subnormals (~1e-40, sign kept)."""
    tensors, manifest = valid_parts(arch, grid=grid)
    for name, t in tensors.items():
        if t.dim() == 4:
            tensors[name] = torch.where(t >= 0, 1e-40, -1e-40).to(torch.float32)
    assert all(((t != 0) & (t.abs() < TINY)).all() for t in tensors.values() if t.dim() == 4)
    return forge(tensors, manifest)


# --- denormals ---------------------------------------------------------------------------

def test_subnormal_weights_are_loaded_as_zero_everywhere(tmp_path) -> None:
    data = _subnormal_bundle()
    for load in (load_bundle, load_untrusted):
        bundle = load(data)
        for name, p in bundle.net.named_parameters():
            assert not ((p != 0) & (p.abs() < TINY)).any(), (load.__name__, name)
        conv_weights = [p for p in bundle.net.parameters() if p.dim() == 4]
        assert conv_weights and all((p == 0).all() for p in conv_weights)
    # medc-inspect loads it the same way (and says nothing false about it).
    path = tmp_path / "denormal.safetensors"
    path.write_bytes(data)
    assert inspect_main([str(path)]) == 0


def test_forward_passes_flush_subnormal_results_and_restore_the_mode() -> None:
    a = torch.tensor([1e-20], dtype=torch.float32)
    assert float(a * a) != 0.0  # IEEE: 1e-40 is a subnormal, not 0
    with flush_denormals():
        if torch.set_flush_denormal(True):  # the CPU has flush-to-zero (x86 with SSE3, arm64)
            assert float(a * a) == 0.0
    assert float(a * a) != 0.0  # training code outside keeps IEEE arithmetic


def test_the_dry_run_uses_observations_with_real_structure(monkeypatch) -> None:
    tensors, manifest = valid_parts("lenet5", grid=10)
    obs = dry_run_observations(manifest, (5, 10, 10))
    assert len(obs) == 3 and all(o.shape == (1, 5, 10, 10) for o in obs)
    blank, real, dense = obs
    assert not blank.any()
    # The environment's own observation: several channels in use, with more than two values.
    assert sum(bool(real[0, c].any()) for c in range(5)) >= 3 and real.unique().numel() > 2
    assert (dense > 0).float().mean() > 0.99
    seen = []
    real_forward = dryrun_mod.timed_forward

    def spy(net, o, mask, limit):
        seen.append(o.clone())
        return real_forward(net, o, mask, limit)

    monkeypatch.setattr("medc_training.bundle.policy.timed_forward", spy)
    load_untrusted(forge(tensors, manifest))
    assert len(seen) == 3 and torch.equal(seen[1], real)


# --- slow bundles --------------------------------------------------------------------------

def _slow_bundle() -> bytes:
    """A slow bundle: 1-channel 64x64 convolutions on a padded-up map, ~418 M operations (just under
    nets.MAX_OPERATIONS); tens of ms a pass on one core of this project's dev machine."""
    tensors, manifest = spec_parts(bomb_spec(5, 10, 3, 62, [conv(1, 64)]))
    gen = torch.Generator().manual_seed(0)
    tensors = {k: torch.rand(v.shape, generator=gen) * 0.01 for k, v in tensors.items()}
    return forge(tensors, manifest)


def _refuse_once(full, blank: torch.Tensor, allowed: torch.Tensor) -> tuple[float, float, object, float]:
    """(one warm pass's seconds, the limit, the TooSlow raised, seconds to raise it). The limit is a
    quarter of a pass, or three times the small padding layers before the big one if they take longer (on
    some machines they are a third of a pass: memory-bound, where the big convolution is not). Each
    layer's time is its fastest of three passes: a stall of a shared machine in one pass is not its cost."""
    times = []
    for _ in range(3):  # warm: the first call of a shape also builds its kernels
        x, layers = blank, []
        with torch.no_grad():
            for module in full.net.trunk:
                start = time.perf_counter()
                x = module(x)
                layers.append(time.perf_counter() - start)
        times.append(layers)
    layers = [min(each) for each in zip(*times, strict=True)]
    one_pass = sum(layers)
    limit = max(one_pass / 4, 3 * sum(layers[:3]))  # "too slow" here, whatever the machine's speed
    assert limit < one_pass, layers  # the big layer is what makes the bundle too slow
    start = time.perf_counter()
    with pytest.raises(dryrun_mod.TooSlow) as slow:
        dryrun_mod.timed_forward(full.net, blank, allowed, limit)
    return one_pass, limit, slow.value, time.perf_counter() - start


#: Tries of a timed refusal, and the pause before each retry: a shared machine's busy spell (the other
#: test worker starting a ROS graph: seconds of CPU) must be over before the next try.
TRIES, RETRY_PAUSE_S = 5, 1.5


@pytest.mark.timing
def test_a_slow_bundle_is_refused_after_about_the_limit_and_a_republish_costs_nothing(
        tmp_path, monkeypatch, one_thread) -> None:
    data = _slow_bundle()
    full = load_bundle(data)
    blank = torch.zeros((1, *full.obs_shape))
    allowed = torch.ones((1, 8), dtype=torch.bool)
    # The big layer (3) is timed on a 1/16 strip of its output first, and the pass abandoned before
    # the layer runs in full. A stall of a shared machine (tens of ms) can refuse the bundle before
    # the estimate, or make the refusal slow: rightly refused, but not the way this test is about,
    # so that case is measured again after a pause (TRIES tries).
    for attempt in range(TRIES):
        time.sleep(RETRY_PAUSE_S if attempt else 0.0)
        one_pass, limit, slow, took = _refuse_once(full, blank, allowed)
        if slow.estimated and took < one_pass:
            break
    assert slow.estimated and slow.layer == 3 and slow.seconds > limit, (slow, limit)
    assert took < one_pass, (took, one_pass)
    first = tmp_path / "slow.safetensors"
    first.write_bytes(data)
    # The dry run's observation of the bundle's environment is built once per process (a few
    # random steps of the scenario, ~0.3 s): built here, so that what is timed is the refusal.
    dryrun_mod.dry_run_observations(full.manifest, full.obs_shape)
    # The dry run refuses it within one pass (no full blank pass first, no second chance). As
    # above, a stall can refuse it another way or slowly: measured again after a pause (TRIES
    # tries, each with the refusals remembered so far forgotten).
    too_slow = r"takes .* s to evaluate, over the .* s limit \(too slow"
    for attempt in range(TRIES):
        time.sleep(RETRY_PAUSE_S if attempt else 0.0)
        policy_mod.forget_refusals()
        start = time.perf_counter()
        with pytest.raises(BundleError, match=too_slow) as info:
            load_untrusted(first, max_forward_s=limit)
        refused_in = time.perf_counter() - start
        estimated = "estimated from a part of layer 3" in str(info.value)
        if estimated and refused_in < one_pass:
            break
    assert str(info.value).startswith(f"{first}: ")
    assert estimated, str(info.value)
    assert refused_in < one_pass, (refused_in, one_pass)
    again = tmp_path / "republished.safetensors"
    shutil.copy(first, again)
    work = []  # every bundle decoded past its header, every timed pass, from here on
    real_load, real_forward = policy_mod._load, policy_mod.timed_forward
    monkeypatch.setattr(policy_mod, "_load", lambda *args: work.append("load") or real_load(*args))
    monkeypatch.setattr(policy_mod, "timed_forward", lambda *args: work.append("pass") or real_forward(*args))
    with pytest.raises(BundleError, match="refused before; not checked again"):
        load_untrusted(again, max_forward_s=limit)
    assert work == []  # refused by its content's digest: neither loaded nor run


def _count_work(monkeypatch) -> list[str]:
    """Every bundle decoded past its header ('load') and every timed pass ('pass') from here on."""
    work: list[str] = []
    real_load, real_forward = policy_mod._load, policy_mod.timed_forward
    monkeypatch.setattr(policy_mod, "_load", lambda *args: work.append("load") or real_load(*args))
    monkeypatch.setattr(policy_mod, "timed_forward", lambda *args: work.append("pass") or real_forward(*args))
    return work


def test_byte_different_copies_of_a_slow_bundle_cost_one_dry_run(monkeypatch) -> None:
    # Under a 1 ns limit every pass is too slow: the refusal is the real one, whatever the machine.
    tensors, manifest = valid_parts("lenet5", grid=10)
    work = _count_work(monkeypatch)
    with pytest.raises(BundleError, match=r"over the 1e-09 s limit \(too slow"):
        load_untrusted(forge(tensors, manifest), max_forward_s=1e-09)
    assert work == ["load", "pass"]
    copies = []
    for i in range(10):  # other descriptions, other weights, another order of the tensors
        edited = {k: (v + 1e-3 * (i + 1) if i % 2 else v.clone()) for k, v in tensors.items()}
        if i % 3 == 0:
            edited = dict(reversed(list(edited.items())))
        copies.append(forge(edited, dict(manifest, description=f"copy {i}")))
    assert len({bytes(c) for c in copies}) == 10
    work.clear()
    for data in copies:
        with pytest.raises(BundleError, match=r"too slow .*\(the same network structure was refused "
                                              r"before; not checked again\)"):
            load_untrusted(data, max_forward_s=1e-09)
    assert work == []  # not one of the ten decoded, let alone run
    # Under the agents' limit the structure is not refused: the memory is per limit.
    assert load_untrusted(copies[0]).manifest["description"] == "copy 0"


def test_dry_runs_of_new_structures_pause_after_three_slow_refusals(monkeypatch) -> None:
    slow = [valid_parts("lenet5", grid=g) for g in (10, 11, 12, 13)]
    work = _count_work(monkeypatch)
    for tensors, manifest in slow[:policy_mod.SLOW_REFUSALS_PER_WINDOW]:
        with pytest.raises(BundleError, match="too slow"):
            load_untrusted(forge(tensors, manifest), max_forward_s=1e-09)
    assert work.count("pass") == policy_mod.SLOW_REFUSALS_PER_WINDOW
    work.clear()
    with pytest.raises(BundleError, match=r"not checked: 3 bundles were too slow to act with in the last "
                                          r"60 s, so dry runs .* are paused for \d+ s"):
        load_untrusted(forge(*slow[3]), max_forward_s=1e-09)
    assert work == []
    # A structure this process accepted before is still checked: it gets its dry run (here refused,
    # every pass being over 1 ns); under another limit nothing is paused.
    tensors, manifest = valid_parts("mlp", grid=10)
    accepted = ("network structure", policy_mod.structure_digest(manifest), 1e-09, "cpu")
    policy_mod._ACCEPTED[accepted] = None
    with pytest.raises(BundleError, match="too slow"):
        load_untrusted(forge(tensors, manifest), max_forward_s=1e-09)
    assert work == ["load", "pass"]
    load_untrusted(forge(*slow[3]))
    # The pause ends with the window.
    monkeypatch.setattr(policy_mod, "SLOW_WINDOW_S", 0.0)
    with pytest.raises(BundleError, match="too slow"):
        load_untrusted(forge(*slow[3]), max_forward_s=1e-09)


@pytest.mark.timing
def test_a_stalled_strip_does_not_refuse_a_bundle_that_is_not_slow(monkeypatch, one_thread) -> None:
    # A shared machine can stall the 1/16 strip a big layer is probed on; scaled up by 16, one stall
    # would refuse a bundle well under the limit. The estimate is taken only if a second strip confirms it.
    full = load_bundle(_slow_bundle())
    blank = torch.zeros((1, *full.obs_shape))
    allowed = torch.ones((1, 8), dtype=torch.bool)
    passes = []
    for _ in range(2):  # warm, then one timed pass
        start = time.perf_counter()
        dryrun_mod.timed_forward(full.net, blank, allowed, float("inf"))
        passes.append(time.perf_counter() - start)
    limit = 4 * passes[-1] + 0.5  # room for a busy machine's stall in the real pass
    real_strip, calls = dryrun_mod._run_strip, []

    def stalled_once(module, part, stride):
        calls.append(part.shape)
        seconds = real_strip(module, part, stride)
        return seconds + (limit if len(calls) == 1 else 0.0)  # the first strip "stalls" a whole limit

    monkeypatch.setattr(dryrun_mod, "_run_strip", stalled_once)
    assert dryrun_mod.timed_forward(full.net, blank, allowed, limit) < limit
    assert len(calls) == 2  # the stalled strip was run again, and its second run counted
    monkeypatch.setattr(dryrun_mod, "_run_strip", real_strip)
    with pytest.raises(dryrun_mod.TooSlow) as slow:  # a limit the layer really passes is still enforced
        dryrun_mod.timed_forward(full.net, blank, allowed, passes[-1] / 50)
    assert slow.value.seconds > passes[-1] / 50


# --- the grid a manifest names -----------------------------------------------------------------

@pytest.mark.parametrize("grid", [10**6, 256, MAX_BUNDLE_GRID + 1, 0, 12.5])
def test_a_manifest_grid_beyond_the_bound_is_refused_by_every_reader(grid, tmp_path, capsys) -> None:
    from medc_training.envs.tl_observation import observation_channels, observation_shape, parse_observation
    from medc_training.nets import make_actor_critic

    # A grid-free observation (an agent-centred window), so the grid is not tied to the input size.
    spec = parse_observation("ego4")
    shape = observation_shape(spec, 10)
    torch.manual_seed(0)
    net = make_actor_critic("lenet5", shape, 8)
    _, manifest = valid_parts("lenet5", grid=10)
    manifest = {**manifest, "environment": {**manifest["environment"], "grid": grid},
                "architecture": net.spec,
                "observation": {"name": spec.name, "channels": shape[0], "height": shape[1],
                                "width": shape[2], "channel_names": list(observation_channels(spec))}}
    data = forge(dict(net.state_dict()), manifest)
    path = tmp_path / "grid.safetensors"
    path.write_bytes(data)
    for load in (read_manifest, load_bundle, load_untrusted):
        with pytest.raises(BundleError, match=rf"environment.grid is .*from 1 to {MAX_BUNDLE_GRID}"):
            load(path)
    assert inspect_main([str(path)]) == 1
    assert f"from 1 to {MAX_BUNDLE_GRID}" in capsys.readouterr().err
    # The same bundle with a grid within the bound loads.
    manifest["environment"]["grid"] = 30
    assert read_manifest(forge(dict(net.state_dict()), manifest))["environment"]["grid"] == 30


def test_a_manifest_team_beyond_the_bound_is_refused() -> None:
    tensors, manifest = valid_parts("lenet5", grid=10)
    manifest = {**manifest, "environment": {**manifest["environment"], "agents": 10**6}}
    with pytest.raises(BundleError, match=f"environment.agents is 1000000.*from 1 to {MAX_BUNDLE_AGENTS}"):
        read_manifest(forge(tensors, manifest))
