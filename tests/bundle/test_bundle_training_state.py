"""Pickle-free training checkpoints: nested state (model, optimizer, RNGs) survives save/load exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from medc_training.bundle import BundleError, load_state, save_state
from medc_training.nets import make_actor_critic


def _train_steps(net, opt, steps: int, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        obs = torch.rand(8, 5, 10, 10, generator=gen)
        logits, value = net(obs)
        loss = logits.logsumexp(-1).mean() + value.pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()


def test_resumed_optimizer_continues_exactly_like_an_uninterrupted_run(tmp_path) -> None:
    torch.manual_seed(0)
    net = make_actor_critic("convnet-small", (5, 10, 10), 8)
    opt = torch.optim.Adam(net.parameters(), lr=3e-4, eps=1e-5)
    _train_steps(net, opt, 3, seed=1)
    path = save_state(tmp_path / "ckpt.safetensors",
                      {"model": net.state_dict(), "optimizer": opt.state_dict(), "step": 3})

    _train_steps(net, opt, 2, seed=2)  # the uninterrupted run

    state = load_state(path)
    assert state["step"] == 3
    resumed = make_actor_critic("convnet-small", (5, 10, 10), 8)
    resumed.load_state_dict(state["model"])
    resumed_opt = torch.optim.Adam(resumed.parameters(), lr=3e-4, eps=1e-5)
    resumed_opt.load_state_dict(state["optimizer"])
    _train_steps(resumed, resumed_opt, 2, seed=2)
    for (name, a), b in zip(net.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name


def test_nested_values_and_rng_states_round_trip(tmp_path) -> None:
    torch_rng = torch.get_rng_state()
    np_legacy = np.random.RandomState(5).get_state()
    generator = np.random.default_rng(9)
    state = {
        "torch_rng": torch_rng,
        "np_legacy": np_legacy,
        "np_generator": generator.bit_generator.state,  # PCG64 state: ints wider than 64 bits
        "counts": np.arange(6, dtype=np.int64).reshape(2, 3),
        "by_id": {0: torch.ones(2), 7: [1.5, None, True, "x"]},
        "betas": (0.9, 0.999),
        "empty": torch.zeros(0),
        "half": torch.tensor([1.0, 2.0], dtype=torch.float16),
    }
    back = load_state(save_state(tmp_path / "s.safetensors", state))
    assert torch.equal(back["torch_rng"], torch_rng)
    restored = np.random.RandomState()
    restored.set_state(back["np_legacy"])
    assert restored.random() == np.random.RandomState(5).random()
    resumed = np.random.default_rng()
    resumed.bit_generator.state = back["np_generator"]
    assert resumed.random() == generator.random()
    assert isinstance(back["counts"], np.ndarray) and np.array_equal(back["counts"], state["counts"])
    assert set(back["by_id"]) == {0, 7} and torch.equal(back["by_id"][0], torch.ones(2))
    assert back["by_id"][7] == [1.5, None, True, "x"]
    assert back["betas"] == (0.9, 0.999)
    assert back["empty"].shape == (0,) and back["half"].dtype == torch.float16


def test_unstorable_values_and_foreign_files_are_clear_errors(tmp_path) -> None:
    with pytest.raises(TypeError, match="cannot store object"):
        save_state(tmp_path / "a.safetensors", {"x": object()})
    with pytest.raises(TypeError, match="dict keys must be"):
        save_state(tmp_path / "b.safetensors", {("a", 1): 2})
    (tmp_path / "c.safetensors").write_bytes(b"\x80\x04garbage")
    with pytest.raises(BundleError, match="not a training checkpoint"):
        load_state(tmp_path / "c.safetensors")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.safetensors"]  # failed saves leave nothing
