"""Actor-critic networks: shapes on every grid size, declarative specs, spec validation, masks."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from medc_training.nets import (
    ARCHITECTURES,
    ActorCritic,
    SpecError,
    architecture_spec,
    make_actor_critic,
    masked_logits,
    spec_tensor_shapes,
    validate_spec,
)


@pytest.mark.parametrize("arch", sorted(ARCHITECTURES))
@pytest.mark.parametrize("grid", [10, 13, 20, 30])
def test_every_architecture_maps_map_stacks_to_logits_and_values(arch: str, grid: int) -> None:
    net = make_actor_critic(arch, obs_shape=(5, grid, grid), num_actions=8)
    logits, value = net(torch.rand(6, 5, grid, grid))
    assert logits.shape == (6, 8) and value.shape == (6,)
    assert torch.isfinite(logits).all() and torch.isfinite(value).all()
    # The loader checks stored tensors against the arithmetic shapes; they must be the real ones.
    assert {k: tuple(v.shape) for k, v in net.state_dict().items()} == spec_tensor_shapes(net.spec)


def test_lenet5_has_the_documented_layers() -> None:
    spec = architecture_spec("lenet5", (5, 30, 30), 8)
    kinds = [layer["type"] for layer in spec["layers"]]
    assert kinds == ["conv2d", "relu", "maxpool2d", "conv2d", "relu", "maxpool2d", "flatten",
                     "linear", "relu", "linear", "relu", "heads"]
    shapes = spec_tensor_shapes(spec)
    assert shapes["trunk.0.weight"] == (6, 5, 5, 5)
    assert shapes["trunk.3.weight"] == (16, 6, 5, 5)
    assert shapes["trunk.7.weight"] == (120, 16 * 8 * 8)  # 30 -> 15 -> 8 with ceil-mode pooling
    assert shapes["trunk.9.weight"] == (84, 120)
    assert shapes["policy.weight"] == (8, 84) and shapes["value.weight"] == (1, 84)


def test_a_net_rebuilt_from_its_spec_computes_the_same_function() -> None:
    net = make_actor_critic("convnet-small", (5, 12, 12), 8)
    clone = make_actor_critic(net.spec)
    clone.load_state_dict(net.state_dict())
    obs = torch.rand(4, 5, 12, 12)
    assert torch.equal(net(obs)[0], clone(obs)[0]) and torch.equal(net(obs)[1], clone(obs)[1])
    spec = net.spec
    spec["layers"].clear()  # the property is a copy: mutating it cannot change the network
    assert net.spec["layers"]


def test_initialisation_is_orthogonal_with_ppo_gains() -> None:
    net = make_actor_critic("mlp", (5, 10, 10), 8)
    w = net.policy.weight.detach()
    assert torch.allclose(w @ w.T, 0.01**2 * torch.eye(8), atol=1e-6)
    hidden = net.trunk[1].weight.detach()  # 128 x 500: rows orthonormal, scaled by sqrt(2)
    assert torch.allclose(hidden @ hidden.T, 2 * torch.eye(128), atol=1e-4)
    assert all(float(b.detach().abs().max()) == 0 for n, b in net.named_parameters() if n.endswith("bias"))


def test_initial_policy_is_near_uniform() -> None:
    net = make_actor_critic("lenet5", (5, 30, 30), 8)
    probs = torch.softmax(net(torch.rand(16, 5, 30, 30))[0], -1)
    assert torch.allclose(probs, torch.full_like(probs, 1 / 8), atol=0.02)


def test_wrong_observation_shape_is_a_clear_error() -> None:
    net = make_actor_critic("lenet5", (5, 10, 10), 8)
    with pytest.raises(ValueError, match=r"expected observations \[M, 5, 10, 10\]"):
        net(torch.rand(2, 5, 12, 12))


def _spec(layers: list, channels: int = 5, side: int = 10) -> dict:
    return {"name": "t", "input": {"channels": channels, "height": side, "width": side}, "layers": layers}


HEADS = {"type": "heads", "num_actions": 8}


@pytest.mark.parametrize(("layers", "message"), [
    ([{"type": "lambda", "code": "import os"}, HEADS], "unknown layer type 'lambda'"),
    ([{"type": "flatten"}, {"type": "linear", "out_features": 4, "activation": "x"}, HEADS], "unknown keys"),
    ([{"type": "linear", "out_features": 4}, HEADS], "add a 'flatten' layer"),
    ([{"type": "flatten"}, HEADS, {"type": "relu"}], "'heads' must be the last layer"),
    ([{"type": "flatten"}, {"type": "relu"}], "last layer must be"),
    ([{"type": "conv2d", "out_channels": 4, "kernel_size": 11}, {"type": "flatten"}, HEADS], "shrinks to"),
    ([{"type": "conv2d", "out_channels": 4}, {"type": "flatten"}, HEADS], "missing required key"),
    ([{"type": "flatten"}, {"type": "linear", "out_features": 2.5}, HEADS], "must be an integer"),
    ([{"type": "flatten"}, {"type": "linear", "out_features": True}, HEADS], "must be an integer"),
    ([{"type": "flatten"}, {"type": "linear", "out_features": 1 << 16},
      {"type": "linear", "out_features": 1000}, HEADS], "exceeds .* parameters"),
    ([{"type": "flatten"}, {"type": "heads", "num_actions": 1}], "num_actions"),
    ([{"type": "flatten"}, {"type": "conv2d", "out_channels": 4, "kernel_size": 3}, HEADS], "already flat"),
])
def test_invalid_specs_are_rejected_with_the_reason(layers: list, message: str) -> None:
    with pytest.raises(SpecError, match=message):
        validate_spec(_spec(layers))


def test_specs_that_would_exhaust_memory_are_rejected_before_allocation() -> None:
    wide = [{"type": "conv2d", "out_channels": 1 << 16, "kernel_size": 1}, {"type": "flatten"}, HEADS]
    with pytest.raises(SpecError, match="values per observation exceeds"):
        validate_spec(_spec(wide, side=30))
    with pytest.raises(SpecError, match="between 1 and 65536"):
        validate_spec(_spec([{"type": "flatten"}, {"type": "linear", "out_features": 1 << 17}, HEADS]))


def test_spec_top_level_is_checked() -> None:
    with pytest.raises(SpecError, match="unknown keys"):
        validate_spec(dict(_spec([{"type": "flatten"}, HEADS]), init="eval('x')"))
    with pytest.raises(SpecError, match="'input' must be"):
        validate_spec({"layers": [{"type": "flatten"}, HEADS]})
    with pytest.raises(ValueError, match="unknown architecture 'resnet'"):
        make_actor_critic("resnet", (5, 10, 10), 8)


@settings(max_examples=60, deadline=None, database=None)
@given(side=st.integers(4, 31), kernel=st.integers(1, 4), stride=st.integers(1, 3), ceil=st.booleans(),
       conv_k=st.integers(1, 5), pad=st.integers(0, 2))
def test_shape_arithmetic_matches_torch(side: int, kernel: int, stride: int, ceil: bool, conv_k: int,
                                        pad: int) -> None:
    layers = [
        {"type": "conv2d", "out_channels": 3, "kernel_size": conv_k, "stride": stride, "padding": pad},
        {"type": "maxpool2d", "kernel_size": kernel, "stride": stride, "ceil_mode": ceil},
        {"type": "flatten"}, HEADS,
    ]
    x = torch.rand(1, 2, side, side)
    try:
        net = ActorCritic(_spec(layers, channels=2, side=side))
    except SpecError:
        # The arithmetic only refuses what torch cannot run (or would run on an empty map).
        try:
            y = torch.nn.functional.conv2d(x, torch.rand(3, 2, conv_k, conv_k), stride=stride, padding=pad)
            y = torch.nn.functional.max_pool2d(y, kernel, stride, ceil_mode=ceil)
        except RuntimeError:
            return
        assert y.numel() == 0, "torch runs a spec the arithmetic refused"
        return
    assert net(x)[0].shape == (1, 8)
    assert net.trunk(x).shape[1] == spec_tensor_shapes(net.spec)["policy.weight"][1]


@settings(max_examples=80, deadline=None, database=None)
@given(data=st.data(), rows=st.integers(1, 6))
def test_masked_logits_never_allow_an_invalid_action(data: st.DataObject, rows: int) -> None:
    values = st.floats(-1e6, 1e6, allow_nan=False, width=32)
    logits = torch.tensor(data.draw(st.lists(st.lists(values, min_size=8, max_size=8),
                                             min_size=rows, max_size=rows)), dtype=torch.float32)
    mask = torch.tensor(data.draw(st.lists(st.lists(st.booleans(), min_size=8, max_size=8),
                                           min_size=rows, max_size=rows)))
    mask[torch.arange(rows), data.draw(st.integers(0, 7))] = True  # environments always allow a move
    masked = masked_logits(logits, mask)
    assert torch.isfinite(masked).all()
    assert mask.gather(1, masked.argmax(-1, keepdim=True)).all()
    dist = torch.distributions.Categorical(logits=masked)
    assert float(dist.probs[~mask].sum()) == 0.0
    assert torch.isfinite(dist.entropy()).all() and torch.isfinite(dist.log_prob(masked.argmax(-1))).all()
    samples = dist.sample((64,))
    assert mask.gather(1, samples.T).all()


def test_masked_logits_keep_gradients_finite_and_reject_non_bool_masks() -> None:
    logits = torch.zeros(2, 8, requires_grad=True)
    mask = torch.zeros(2, 8, dtype=torch.bool)
    mask[:, 3] = True
    dist = torch.distributions.Categorical(logits=masked_logits(logits, mask))
    (dist.log_prob(torch.tensor([3, 3])).sum() + dist.entropy().sum()).backward()
    assert torch.isfinite(logits.grad).all()
    with pytest.raises(TypeError, match="bool"):
        masked_logits(logits, mask.float())
    half = masked_logits(torch.zeros(1, 8, dtype=torch.float16), mask[:1])
    assert torch.isfinite(half).all() and math.isclose(float(torch.softmax(half.float(), -1)[0, 3]), 1.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_networks_run_on_cuda() -> None:
    net = make_actor_critic("lenet5", (5, 30, 30), 8, device="cuda")
    logits, value = net(torch.rand(3, 5, 30, 30, device="cuda"))
    assert logits.is_cuda and value.shape == (3,)
