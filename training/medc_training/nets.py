"""Actor-critic networks for the MEDC teams, described declaratively.

A network maps an agent's map stack ``obs`` float32 ``[M, C, H, W]`` to action logits ``[M, A]``
and a state value ``[M]``; one network is shared by all the agents of a team. Every architecture is
a JSON-able *spec* built only from a closed set of layer types (``LAYER_TYPES``), and every tensor
shape follows from the spec by arithmetic (``spec_tensor_shapes``), so a policy bundle is rebuilt
from its manifest and checked before any weight reaches torch, without running code from the file.
The layer types, the built-in architectures (``ARCHITECTURES``) and the initialisation:
docs/bundles.md, "Networks".
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from medc_training.untrusted import printable

LAYER_TYPES = ("conv2d", "maxpool2d", "relu", "tanh", "flatten", "linear", "heads")

# Keys each layer type accepts: required keys map to None, optional ones to their default.
_LAYER_KEYS: dict[str, dict[str, Any]] = {
    "conv2d": {"out_channels": None, "kernel_size": None, "stride": 1, "padding": 0},
    "maxpool2d": {"kernel_size": None, "stride": None, "ceil_mode": False},
    "relu": {},
    "tanh": {},
    "flatten": {},
    "linear": {"out_features": None},
    "heads": {"num_actions": None},
}

# Guards against specs that would allocate absurd amounts of memory when rebuilt (a bundle from a
# stranger is data; its spec must not be able to exhaust the machine).
MAX_PARAMETERS = 50_000_000
MAX_INPUT_SIDE = 4096
MAX_CHANNELS = 4096
MAX_ACTIONS = 4096
MAX_ACTIVATIONS = 1 << 24  # elements of any one layer's output for a single observation (64 MiB)
# Compute and memory caps per observation, from the spec alone (``architecture_cost``). The shipped
# architectures need at most 12.6 M operations and 0.5 MiB (convnet-small on a 61x61x8 window or a
# 64x64 grid; 2.7 M and 0.11 MiB at the paper's 30x30): the caps leave margins of ~40x and 64x.
# Even a 256x256 grid (the largest target_localization accepts) fits: 185 M and 8 MiB.
MAX_OPERATIONS = 500_000_000
MAX_ACTIVATION_BYTES = 32 << 20

# Large negative logit for masked-out actions: exp() of it is exactly 0, yet it stays finite so
# entropies and log-probabilities never produce NaN (0 * -inf).
_MASK_LOGIT = -1e9


class SpecError(ValueError):
    """The architecture spec is malformed, uses an unknown layer, or its shapes do not fit."""


def safe_repr(value: Any, limit: int = 40) -> str:
    """A short, printable description of a value taken from an untrusted file, for messages.

    Strings are quoted with every character outside printable ASCII (controls, ANSI escapes,
    quotes, backslashes, any non-ASCII) shown as ``?`` and cut to ``limit`` characters; numbers
    are shown cut to ``limit`` characters; containers only by their type. A message built with
    this never carries more than a few dozen characters of the file, and nothing a terminal or
    log reader would interpret.
    """
    if isinstance(value, str):
        return "'" + printable(value, limit, drop="'\\\"") + "'"
    if value is None or isinstance(value, bool):
        return repr(value)
    if isinstance(value, int | float):
        text = repr(value) if not isinstance(value, int) or abs(value) < 10 ** limit else "a huge integer"
        return text if len(text) <= limit else text[:limit] + "..."
    if isinstance(value, Mapping):
        return "an object"
    if isinstance(value, list | tuple):
        return "a list"
    return f"a {type(value).__name__}"


def safe_names(values: Any, limit: int = 3) -> str:
    """``[...]`` of at most ``limit`` sanitised names (see ``safe_repr``), then how many more."""
    items = sorted(values, key=str) if isinstance(values, set | frozenset) else list(values)
    shown = ", ".join(safe_repr(v) for v in items[:limit])
    more = f", and {len(items) - limit} more" if len(items) > limit else ""
    return f"[{shown}{more}]"


def _conv_out(size: int, kernel: int, stride: int, padding: int) -> int:
    return (size + 2 * padding - kernel) // stride + 1


def _pool_out(size: int, kernel: int, stride: int, ceil_mode: bool) -> int:
    if not ceil_mode:
        return (size - kernel) // stride + 1
    out = math.ceil((size - kernel) / stride) + 1
    # torch drops the last window if it would start entirely in the (virtual) right padding.
    if (out - 1) * stride >= size:
        out -= 1
    return out


def _positive_int(value: Any, where: str, key: str, *, minimum: int = 1, maximum: int | None = None) -> int:
    # bool is an int subclass; true/false is never a valid size.
    if isinstance(value, bool) or not isinstance(value, int):
        raise SpecError(f"{where}: '{key}' must be an integer, got {safe_repr(value)}")
    if value < minimum or (maximum is not None and value > maximum):
        bound = f"between {minimum} and {maximum}" if maximum is not None else f">= {minimum}"
        raise SpecError(f"{where}: '{key}' must be {bound}, got {value}")
    return value


def _normalise_layer(raw: Any, index: int) -> dict[str, Any]:
    """Check one layer's type and keys; return it with defaults filled in."""
    where = f"layer {index}"
    if not isinstance(raw, Mapping):
        raise SpecError(f"{where}: expected an object with a 'type', got {type(raw).__name__}")
    kind = raw.get("type")
    if kind not in _LAYER_KEYS:
        raise SpecError(f"{where}: unknown layer type {safe_repr(kind)}; allowed: {', '.join(LAYER_TYPES)}")
    allowed = _LAYER_KEYS[kind]
    extra = sorted(set(raw) - set(allowed) - {"type"}, key=str)
    if extra:
        raise SpecError(f"{where} ({kind}): unknown keys {safe_names(extra)}; "
                        f"allowed: {sorted(allowed) or 'none'}")
    layer: dict[str, Any] = {"type": kind}
    for key, default in allowed.items():
        if key in raw:
            layer[key] = raw[key]
        elif default is None and not (kind == "maxpool2d" and key == "stride"):
            raise SpecError(f"{where} ({kind}): missing required key '{key}'")
        else:
            layer[key] = default
    if kind == "maxpool2d" and layer["stride"] is None:
        layer["stride"] = layer["kernel_size"]
    for key in ("out_channels", "out_features"):
        if key in layer:
            _positive_int(layer[key], where, key, maximum=1 << 16)
    if kind == "heads":
        _positive_int(layer["num_actions"], where, "num_actions", minimum=2, maximum=MAX_ACTIONS)
    if kind in ("conv2d", "maxpool2d"):
        _positive_int(layer["kernel_size"], where, "kernel_size", maximum=64)
        _positive_int(layer["stride"], where, "stride", maximum=64)
    if kind == "conv2d":
        _positive_int(layer["padding"], where, "padding", minimum=0, maximum=64)
    if kind == "maxpool2d" and not isinstance(layer["ceil_mode"], bool):
        raise SpecError(f"{where} (maxpool2d): 'ceil_mode' must be true or false")
    return layer


def validate_spec(spec: Any) -> dict[str, Any]:
    """Check an architecture spec completely and return a normalised copy (defaults filled in).

    Raises ``SpecError`` (a ``ValueError``) naming the offending layer for: a non-object spec,
    unknown keys, unknown layer types, missing or non-integer sizes, shapes that collapse to zero,
    a ``linear`` applied before ``flatten``, a missing/misplaced ``heads`` layer, or a network
    larger than ``MAX_PARAMETERS``. Nothing is allocated; this is pure arithmetic.
    """
    if not isinstance(spec, Mapping):
        raise SpecError(f"architecture spec must be an object, got {type(spec).__name__}")
    extra = sorted(set(spec) - {"name", "input", "layers"}, key=str)
    if extra:
        raise SpecError(f"architecture spec: unknown keys {safe_names(extra)}; "
                        "allowed: ['input', 'layers', 'name']")
    name = spec.get("name", "custom")
    if not isinstance(name, str) or not name or len(name) > 64:
        raise SpecError("architecture spec: 'name' must be a non-empty string of at most 64 characters")
    inp = spec.get("input")
    if not isinstance(inp, Mapping) or set(inp) != {"channels", "height", "width"}:
        raise SpecError("architecture spec: 'input' must be {'channels': C, 'height': H, 'width': W}")
    channels = _positive_int(inp["channels"], "input", "channels", maximum=MAX_CHANNELS)
    height = _positive_int(inp["height"], "input", "height", maximum=MAX_INPUT_SIDE)
    width = _positive_int(inp["width"], "input", "width", maximum=MAX_INPUT_SIDE)
    raw_layers = spec.get("layers")
    if not isinstance(raw_layers, Sequence) or isinstance(raw_layers, str) or not raw_layers:
        raise SpecError("architecture spec: 'layers' must be a non-empty list")
    if len(raw_layers) > 256:
        raise SpecError(f"architecture spec: at most 256 layers, got {len(raw_layers)}")
    layers = [_normalise_layer(raw, i) for i, raw in enumerate(raw_layers)]
    normalised = {
        "name": name,
        "input": {"channels": channels, "height": height, "width": width},
        "layers": layers,
    }
    spec_tensor_shapes(normalised)  # shape propagation raises on anything that does not fit
    return normalised


def spec_tensor_shapes(spec: Mapping[str, Any]) -> dict[str, tuple[int, ...]]:
    """Names and shapes of every parameter tensor of the network ``spec`` describes.

    Raises ``SpecError`` when the layers do not fit together or the network is too large (more
    than ``MAX_PARAMETERS`` parameters, a layer output above ``MAX_ACTIVATIONS`` values, more than
    ``MAX_OPERATIONS`` operations or ``MAX_ACTIVATION_BYTES`` of activations per observation: see
    ``architecture_cost``).

    ``spec`` must have its defaults filled in (``validate_spec`` output). This is the single source
    of truth a bundle loader checks stored tensors against.
    """
    return _propagate(spec)[0]


@dataclass(frozen=True)
class ArchitectureCost:
    """What one observation costs a network, computed from its spec alone (nothing is allocated).

    ``operations``: multiply-adds of every conv2d, linear and heads layer, plus one per window
    element a maxpool2d compares, plus one per value each layer reads (after padding) and writes:
    a network of cheap layers on huge maps costs what it moves. ``peak_activation_bytes``: the most
    float32 memory one layer holds at once for one observation (its padded input plus its output).
    ``parameters``: the number of weights and biases.
    """

    operations: int
    peak_activation_bytes: int
    parameters: int


def architecture_cost(spec: Mapping[str, Any]) -> ArchitectureCost:
    """The per-observation cost of the network ``spec`` (``validate_spec`` output) describes.

    ``validate_spec`` refuses a spec over ``MAX_OPERATIONS`` or ``MAX_ACTIVATION_BYTES``, so this
    is how to see how close a spec comes to the caps.
    """
    return _propagate(spec, enforce=False)[1]


def _propagate(spec: Mapping[str, Any], enforce: bool = True
               ) -> tuple[dict[str, tuple[int, ...]], ArchitectureCost]:
    shape: tuple[int, ...] = (spec["input"]["channels"], spec["input"]["height"], spec["input"]["width"])
    tensors: dict[str, tuple[int, ...]] = {}
    layers = spec["layers"]
    total = operations = peak = 0
    for i, layer in enumerate(layers):
        kind = layer["type"]
        where = f"layer {i} ({kind})"
        read = math.prod(shape)  # values the layer reads (its padded input for a convolution)
        if kind == "heads":
            if i != len(layers) - 1:
                raise SpecError(f"{where}: 'heads' must be the last layer")
            if len(shape) != 1:
                raise SpecError(f"{where}: needs flat features; add a 'flatten' layer before it")
            features, actions = shape[0], layer["num_actions"]
            tensors.update({
                "policy.weight": (actions, features), "policy.bias": (actions,),
                "value.weight": (1, features), "value.bias": (1,),
            })
            total += (actions + 1) * (features + 1)
            operations += (actions + 1) * features
            out_shape: tuple[int, ...] = (actions + 1,)
        elif kind in ("conv2d", "maxpool2d"):
            if len(shape) != 3:
                raise SpecError(f"{where}: needs a [C, H, W] map stack but the input is already flat")
            c, h, w = shape
            k, s = layer["kernel_size"], layer["stride"]
            if kind == "conv2d":
                p = layer["padding"]
                oh, ow = _conv_out(h, k, s, p), _conv_out(w, k, s, p)
                out = layer["out_channels"]
                tensors[f"trunk.{i}.weight"] = (out, c, k, k)
                tensors[f"trunk.{i}.bias"] = (out,)
                total += out * c * k * k + out
                read = c * (h + 2 * p) * (w + 2 * p)
                if oh >= 1 and ow >= 1:
                    operations += out * c * k * k * oh * ow
                c = out
            else:
                oh = _pool_out(h, k, s, layer["ceil_mode"])
                ow = _pool_out(w, k, s, layer["ceil_mode"])
                if oh >= 1 and ow >= 1:
                    operations += c * oh * ow * k * k
            if oh < 1 or ow < 1:
                raise SpecError(
                    f"{where}: a {h}x{w} input shrinks to {oh}x{ow}; use padding or a smaller kernel"
                )
            shape = out_shape = (c, oh, ow)
        elif kind == "flatten":
            shape = out_shape = (math.prod(shape),)
        elif kind == "linear":
            if len(shape) != 1:
                raise SpecError(f"{where}: needs flat features; add a 'flatten' layer before it")
            out = layer["out_features"]
            tensors[f"trunk.{i}.weight"] = (out, shape[0])
            tensors[f"trunk.{i}.bias"] = (out,)
            total += out * shape[0] + out
            operations += out * shape[0]
            shape = out_shape = (out,)
        else:  # relu, tanh: elementwise
            out_shape = shape
        written = math.prod(out_shape)
        operations += read + written
        peak = max(peak, 4 * (read + written))
        if enforce:
            _check_caps(where, i, shape, ArchitectureCost(operations, peak, total))
    if not layers or layers[-1]["type"] != "heads":
        raise SpecError("architecture spec: the last layer must be {'type': 'heads', 'num_actions': A}")
    return tensors, ArchitectureCost(operations, peak, total)


def _check_caps(where: str, i: int, shape: tuple[int, ...], cost: ArchitectureCost) -> None:
    """SpecError when layers 0..``i`` (the last one ``where``, its output ``shape``) cost more than
    a spec may: parameters, activations, activation bytes or operations."""
    if cost.parameters > MAX_PARAMETERS:
        raise SpecError(f"{where}: the network exceeds {MAX_PARAMETERS:,} parameters")
    if math.prod(shape) > MAX_ACTIVATIONS:
        raise SpecError(f"{where}: its output of {math.prod(shape):,} values per observation "
                        f"exceeds {MAX_ACTIVATIONS:,}")
    if cost.peak_activation_bytes > MAX_ACTIVATION_BYTES:
        raise SpecError(f"{where}: holds {cost.peak_activation_bytes:,} bytes of activations for one "
                        f"observation, over the {MAX_ACTIVATION_BYTES:,} byte limit (a memory bomb, or far "
                        "larger than any MEDC policy)")
    if cost.operations > MAX_OPERATIONS:
        raise SpecError(f"{where}: layers 0..{i} already cost {cost.operations:,} operations per "
                        f"observation, over the {MAX_OPERATIONS:,} limit (a compute bomb, or "
                        "far larger than any MEDC policy)")


def _lenet5(channels: int, height: int, width: int, num_actions: int) -> list[dict[str, Any]]:
    return [
        {"type": "conv2d", "out_channels": 6, "kernel_size": 5, "stride": 1, "padding": 2},
        {"type": "relu"},
        {"type": "maxpool2d", "kernel_size": 2, "stride": 2, "ceil_mode": True},
        {"type": "conv2d", "out_channels": 16, "kernel_size": 5, "stride": 1, "padding": 2},
        {"type": "relu"},
        {"type": "maxpool2d", "kernel_size": 2, "stride": 2, "ceil_mode": True},
        {"type": "flatten"},
        {"type": "linear", "out_features": 120},
        {"type": "relu"},
        {"type": "linear", "out_features": 84},
        {"type": "relu"},
        {"type": "heads", "num_actions": num_actions},
    ]


LayerBuilder = Callable[[int, int, int, int], list[dict[str, Any]]]
"""``(C, H, W, A) -> layers``: a built-in architecture's layer list for the given shapes."""


def _convnet_of_width(first: int, second: int, hidden: int) -> LayerBuilder:
    """Three 3x3 convolutions (``first`` channels at full resolution, then ``second`` at stride 2,
    twice), one hidden layer of ``hidden`` units, the heads."""
    def build(channels: int, height: int, width: int, num_actions: int) -> list[dict[str, Any]]:
        return [
            {"type": "conv2d", "out_channels": first, "kernel_size": 3, "stride": 1, "padding": 1},
            {"type": "relu"},
            {"type": "conv2d", "out_channels": second, "kernel_size": 3, "stride": 2, "padding": 1},
            {"type": "relu"},
            {"type": "conv2d", "out_channels": second, "kernel_size": 3, "stride": 2, "padding": 1},
            {"type": "relu"},
            {"type": "flatten"},
            {"type": "linear", "out_features": hidden},
            {"type": "relu"},
            {"type": "heads", "num_actions": num_actions},
        ]
    return build


def _mlp_of_width(width: int) -> LayerBuilder:
    def build(channels: int, height: int, grid_width: int, num_actions: int) -> list[dict[str, Any]]:
        return [
            {"type": "flatten"},
            {"type": "linear", "out_features": width},
            {"type": "tanh"},
            {"type": "linear", "out_features": width},
            {"type": "tanh"},
            {"type": "heads", "num_actions": num_actions},
        ]
    return build


ARCHITECTURES: dict[str, LayerBuilder] = {
    "lenet5": _lenet5,
    "convnet-small": _convnet_of_width(16, 32, 128),
    "convnet-wide": _convnet_of_width(32, 64, 256),
    "mlp": _mlp_of_width(128),
    "mlp-wide": _mlp_of_width(256),
}
"""Built-in architecture names -> layer-list builders ``(C, H, W, A) -> layers``."""


def architecture_spec(name: str, obs_shape: Sequence[int], num_actions: int) -> dict[str, Any]:
    """The validated declarative spec of built-in architecture ``name`` for the given shapes."""
    if name not in ARCHITECTURES:
        raise ValueError(f"unknown architecture {name!r}; built-in: {', '.join(ARCHITECTURES)}")
    if len(obs_shape) != 3:
        raise ValueError(f"obs_shape must be (C, H, W), got {tuple(obs_shape)}")
    c, h, w = (int(x) for x in obs_shape)
    return validate_spec({
        "name": name,
        "input": {"channels": c, "height": h, "width": w},
        "layers": ARCHITECTURES[name](c, h, w, int(num_actions)),
    })


def _orthogonal(layer: nn.Linear | nn.Conv2d, gain: float) -> None:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)


def _no_init(layer: nn.Linear | nn.Conv2d, gain: float) -> None:
    pass


class ActorCritic(nn.Module):
    """Shared-trunk actor-critic built from a declarative spec (see the module docstring).

    ``forward(obs [M, C, H, W]) -> (logits [M, A], value [M])``. ``spec`` returns a deep copy of
    the normalised JSON spec; ``obs_shape`` and ``num_actions`` come from it. ``initialize=False``
    skips the orthogonal initialisation (for a loader that overwrites every weight anyway).
    """

    def __init__(self, spec: Mapping[str, Any], initialize: bool = True) -> None:
        super().__init__()
        init = _orthogonal if initialize else _no_init
        self._spec = validate_spec(spec)
        inp = self._spec["input"]
        self.obs_shape: tuple[int, int, int] = (inp["channels"], inp["height"], inp["width"])
        in_shape: tuple[int, ...] = self.obs_shape
        modules: list[nn.Module] = []
        for layer in self._spec["layers"][:-1]:
            kind = layer["type"]
            if kind == "conv2d":
                conv = nn.Conv2d(in_shape[0], layer["out_channels"], layer["kernel_size"],
                                 stride=layer["stride"], padding=layer["padding"])
                init(conv, math.sqrt(2))
                modules.append(conv)
            elif kind == "maxpool2d":
                modules.append(nn.MaxPool2d(layer["kernel_size"], stride=layer["stride"],
                                            ceil_mode=layer["ceil_mode"]))
            elif kind == "relu":
                modules.append(nn.ReLU())
            elif kind == "tanh":
                modules.append(nn.Tanh())
            elif kind == "flatten":
                modules.append(nn.Flatten())
            elif kind == "linear":
                lin = nn.Linear(in_shape[0], layer["out_features"])
                init(lin, math.sqrt(2))
                modules.append(lin)
            in_shape = _shape_after(in_shape, layer)
        self.trunk = nn.Sequential(*modules)
        self.num_actions: int = self._spec["layers"][-1]["num_actions"]
        self.policy = nn.Linear(in_shape[0], self.num_actions)
        self.value = nn.Linear(in_shape[0], 1)
        init(self.policy, 0.01)
        init(self.value, 1.0)

    @property
    def spec(self) -> dict[str, Any]:
        """The JSON-able declarative architecture (a copy; editing it does not change the net)."""
        return copy.deepcopy(self._spec)

    @property
    def name(self) -> str:
        return self._spec["name"]

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Map ``obs`` float32 ``[M, C, H, W]`` to ``(logits [M, A], value [M])``."""
        if obs.dim() != 4 or tuple(obs.shape[1:]) != self.obs_shape:
            raise ValueError(
                f"{self.name}: expected observations [M, {', '.join(map(str, self.obs_shape))}], "
                f"got {list(obs.shape)}"
            )
        features = self.trunk(obs)
        return self.policy(features), self.value(features).squeeze(-1)

    def extra_repr(self) -> str:
        return f"name={self.name!r}, obs_shape={self.obs_shape}, num_actions={self.num_actions}"


def _shape_after(shape: tuple[int, ...], layer: Mapping[str, Any]) -> tuple[int, ...]:
    kind = layer["type"]
    if kind == "conv2d":
        k, s, p = layer["kernel_size"], layer["stride"], layer["padding"]
        return (layer["out_channels"], _conv_out(shape[1], k, s, p), _conv_out(shape[2], k, s, p))
    if kind == "maxpool2d":
        k, s, c = layer["kernel_size"], layer["stride"], layer["ceil_mode"]
        return (shape[0], _pool_out(shape[1], k, s, c), _pool_out(shape[2], k, s, c))
    if kind == "flatten":
        return (math.prod(shape),)
    if kind == "linear":
        return (layer["out_features"],)
    return shape


def make_actor_critic(
    arch: str | Mapping[str, Any] = "lenet5",
    obs_shape: Sequence[int] | None = None,
    num_actions: int | None = None,
    device: torch.device | str | None = None,
) -> ActorCritic:
    """Build an actor-critic from a built-in name (with ``obs_shape`` and ``num_actions``) or from a
    declarative spec dict (its own ``input`` and ``heads`` define the shapes; if ``obs_shape`` /
    ``num_actions`` are also given they must agree). ``device`` moves the net there.
    """
    if isinstance(arch, str):
        if obs_shape is None or num_actions is None:
            raise ValueError(f"architecture {arch!r} needs obs_shape=(C, H, W) and num_actions")
        net = ActorCritic(architecture_spec(arch, obs_shape, num_actions))
    elif isinstance(arch, Mapping):
        net = ActorCritic(arch)
        if obs_shape is not None and tuple(obs_shape) != net.obs_shape:
            raise ValueError(f"spec input is {net.obs_shape} but obs_shape={tuple(obs_shape)}")
        if num_actions is not None and num_actions != net.num_actions:
            raise ValueError(f"spec has {net.num_actions} actions but num_actions={num_actions}")
    else:
        raise TypeError(f"arch must be an architecture name or a spec dict, got {type(arch).__name__}")
    return net.to(device) if device is not None else net


def masked_logits(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Logits with disallowed actions (``mask`` False) set to a large finite negative value.

    ``mask`` is bool ``[..., A]`` broadcastable to ``logits``. Softmax then gives disallowed
    actions probability exactly 0 and argmax never picks one, while staying NaN-free in entropy and
    log-prob computations. A row with no allowed action at all becomes uniform (every entry equal);
    environments guarantee at least one allowed move, so this is never a valid sample.
    """
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor (True = allowed), got {mask.dtype}")
    fill = max(_MASK_LOGIT, torch.finfo(logits.dtype).min / 2)
    return logits.masked_fill(~mask, fill)
