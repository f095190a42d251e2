"""medc_training.bundle.runtime: a bundle's network in onnxruntime makes the greedy moves PyTorch
makes on real observations; where onnxruntime is missing or disagrees, ``auto`` runs PyTorch and
says why, and ``onnxruntime`` refuses with the reason."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from medc_training.bundle import load_untrusted
from medc_training.bundle import runtime as rt
from medc_training.radbench.play import BenchCore
from medc_training.radbench.sets import load_sets

ROOT = Path(__file__).resolve().parents[2]
WINDOW9 = ROOT / "docs/reproduction/learned-team/main-posterior-cnn9-ft/medc-s0/policy.safetensors"
MLP = ROOT / "models" / "team" / "A3W2.safetensors"


def benchmark_views(bundle, episodes: int = 6, steps: int = 12):
    """(observations [M,C,H,W], masks [M,A]) of every agent along benchmark episodes, the team moving
    by its own greedy choices."""
    (s,) = load_sets(20, 3, obstructions=[5], snrs=["low"])
    core = BenchCore(s.head(episodes), list(range(episodes)), observation=bundle.observation)
    obs, mask = core.reset()
    views, masks = [obs.flatten(0, 1)], [mask.flatten(0, 1)]
    for _ in range(steps):
        actions = bundle.act(obs.flatten(0, 1), mask.flatten(0, 1)).view(mask.shape[:2])
        step = core.step(actions)
        obs, mask = step.obs, step.mask
        views.append(obs.flatten(0, 1))
        masks.append(mask.flatten(0, 1))
    return torch.cat(views), torch.cat(masks)


@pytest.mark.parametrize("path", [WINDOW9, MLP], ids=["convnet-window9", "mlp"])
def test_onnxruntime_makes_the_moves_pytorch_makes(path):
    bundle = load_untrusted(path)
    if bundle.observation == "maps" or bundle.manifest["environment"].get("world") != "radbench":
        obs = torch.rand((64, *bundle.obs_shape), generator=torch.Generator().manual_seed(1))
        mask = torch.rand((64, bundle.num_actions), generator=torch.Generator().manual_seed(2)) > 0.3
        mask[:, 0] = True
    else:
        obs, mask = benchmark_views(bundle)
    fast = rt.decider(bundle, "onnxruntime")
    assert fast.runtime == "onnxruntime" and fast.note is None
    (logits, value), (want_logits, want_value) = fast.heads(obs), rt.decider(bundle, "torch").heads(obs)
    assert float((logits - want_logits).abs().max()) <= rt.ATOL
    assert float((value - want_value).abs().max()) <= rt.ATOL
    assert torch.equal(fast.act(obs, mask), bundle.act(obs, mask, greedy=True))
    assert torch.equal(fast.act(obs[:1]), bundle.act(obs[:1], greedy=True))  # batch 1, no mask
    with pytest.raises(ValueError, match="mask must have shape"):
        fast.act(obs[:2], mask[:1])


def test_auto_takes_onnxruntime_and_torch_is_pytorchs_own():
    bundle = load_untrusted(MLP)
    assert rt.decider(bundle).runtime == "onnxruntime"
    plain = rt.decider(bundle, "torch")
    assert plain.runtime == "torch" and plain.note is None
    with pytest.raises(ValueError, match="runtime must be one of"):
        rt.decider(bundle, "tensorrt")


def test_without_onnxruntime_auto_runs_pytorch_and_says_why(monkeypatch):
    bundle = load_untrusted(MLP)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import onnxruntime raises ImportError
    auto = rt.decider(bundle)
    assert auto.runtime == "torch" and "onnxruntime is not installed" in auto.note
    obs = torch.rand((5, *bundle.obs_shape), generator=torch.Generator().manual_seed(0))
    assert torch.equal(auto.act(obs), bundle.act(obs))
    with pytest.raises(rt.RuntimeUnavailable, match="not installed"):
        rt.decider(bundle, "onnxruntime")


def test_a_runtime_that_disagrees_with_pytorch_is_not_used(monkeypatch):
    """The agreement check is real: with a tolerance no float can meet, onnxruntime is refused on the
    first probe observation, with the size of the difference."""
    bundle = load_untrusted(MLP)
    monkeypatch.setattr(rt, "ATOL", -1.0)
    with pytest.raises(rt.RuntimeUnavailable, match="differ from PyTorch's by"):
        rt.decider(bundle, "onnxruntime")
    assert rt.decider(bundle).runtime == "torch"


def test_radbench_names_the_runtimes_of_the_module():
    from medc_training.cli import radbench

    assert radbench.RUNTIMES == rt.RUNTIMES


def test_deciding_leaves_the_threads_subnormals_as_they_were():
    """Both runtimes decide with flush-to-zero on and restore IEEE subnormals after (training code
    in the same thread keeps them)."""
    bundle = load_untrusted(MLP)
    obs = torch.rand((2, *bundle.obs_shape), generator=torch.Generator().manual_seed(0))
    tiny = torch.tensor([1e-20], dtype=torch.float32)
    for runtime in ("onnxruntime", "torch"):
        rt.decider(bundle, runtime).act(obs)
        assert float(tiny * tiny) != 0.0, runtime


def test_agreement_counts_every_decision_of_every_episode_played_to_its_end(capsys):
    from medc_training.radbench.cost import main, runtime_agreement
    from medc_training.radbench.play import play_set

    (s,) = load_sets(20, 3, obstructions=[5], snrs=["low"])
    s = s.head(5)
    found = runtime_agreement([s], WINDOW9, batch=3)  # two batches: 3 + 2 episodes
    lengths = [r.length for r in play_set(s, WINDOW9)]
    assert found["decisions"] == 3 * sum(lengths)  # each agent's move at each step of each episode
    assert found["runtime"] == "onnxruntime" and found["differ"] == 0 and found["max_logit_gap"] <= rt.ATOL
    with pytest.raises(ValueError, match="for a bundle"):
        runtime_agreement([s], "greedy")
    assert main(["--agreement", str(WINDOW9), "--episodes", "1"]) == 0
    assert "greedy moves differ" in capsys.readouterr().out
    assert main(["--agreement", "greedy", "--episodes", "1"]) == 2


def test_a_process_running_a_bundle_in_onnxruntime_leaves_no_temporary_file(tmp_path):
    """onnxruntime's telemetry library writes a session file into the temporary folder when imported;
    the decider imports it so that nothing is left there."""
    import os
    import subprocess

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    code = ("import torch; from medc_training.bundle import load_untrusted; "
            "from medc_training.bundle.runtime import decider; "
            f"b = load_untrusted({str(MLP)!r}); d = decider(b); d.act(torch.zeros(1, *b.obs_shape)); "
            "print(d.runtime)")
    done = subprocess.run([sys.executable, "-c", code], env=os.environ | {"TMPDIR": str(scratch)},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "onnxruntime", done.stderr[-2000:]
    assert sorted(p.name for p in scratch.iterdir()) == []
