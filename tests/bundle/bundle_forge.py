"""Helpers that hand-craft (possibly invalid) bundle bytes, bypassing every check of save_bundle."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from typing import Any

import torch
from medc_training.bundle import MANIFEST_KEY, bundle_bytes
from medc_training.nets import make_actor_critic
from safetensors.torch import save as st_save

MANIFEST = {
    "application": "target_localization",
    "description": "test expert",
    "environment": {"agents": 3, "walls": 2, "grid": 10, "max_steps": 100},
    "training": {"method": "sparse", "steps": 4000, "seed": 7},
    "metrics": {"mean_episode_length": 41.5, "success_rate": 0.8},
}


def valid_parts(arch: str = "lenet5", grid: int = 10) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Tensors and complete manifest of a valid bundle, as separate editable objects."""
    torch.manual_seed(0)
    net = make_actor_critic(arch, (5, grid, grid), 8)
    manifest = dict(MANIFEST, environment=dict(MANIFEST["environment"], grid=grid))
    data = bundle_bytes(net, manifest)
    n = struct.unpack("<Q", data[:8])[0]
    full = json.loads(json.loads(data[8:8 + n])["__metadata__"][MANIFEST_KEY])
    tensors = {k: v.detach().clone() for k, v in net.state_dict().items()}
    return tensors, full


def forge(tensors: dict[str, torch.Tensor], manifest: Any, *, raw_manifest: str | None = None) -> bytes:
    """A safetensors file with these tensors and this manifest, valid or not."""
    text = raw_manifest if raw_manifest is not None else json.dumps(manifest)
    return st_save(tensors, metadata={MANIFEST_KEY: text})


def rewrite_header(data: bytes, edit: Callable[[dict[str, Any]], Any]) -> bytes:
    """Re-encode ``data`` after ``edit`` mutates (or replaces, by returning) its parsed header."""
    n = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8:8 + n])
    replaced = edit(header)
    header = header if replaced is None else replaced
    text = json.dumps(header).encode()
    return struct.pack("<Q", len(text)) + text + data[8 + n:]


def raw_header(text: bytes, body: bytes = b"") -> bytes:
    """Length prefix + arbitrary header bytes + arbitrary body."""
    return struct.pack("<Q", len(text)) + text + body


def nested(depth: int, kind: str = "list") -> Any:
    """JSON text nesting ``depth`` levels: lists ``[[[...]]]`` or objects ``{"a": {"a": ...}}``."""
    if kind == "list":
        return "[" * depth + "]" * depth
    return '{"a": ' * depth + "1" + "}" * depth


def with_raw_section(manifest: dict[str, Any], section: str, raw_json: str) -> str:
    """The manifest's JSON text with ``section`` replaced by ``raw_json`` (spliced in as text, so
    a nesting no json.dumps could write is possible)."""
    marker = "__RAW_SECTION__"
    text = json.dumps({**manifest, section: marker})
    return text.replace(json.dumps(marker), raw_json, 1)


def spec_parts(spec: dict[str, Any], grid: int | None = None
               ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Zero tensors and a complete manifest for any architecture ``spec``, valid or not: a forged
    bundle that passes every check but the one under test (e.g. a compute bomb)."""
    from medc_training import nets

    spec = {**spec, "layers": [nets._normalise_layer(raw, i) for i, raw in enumerate(spec["layers"])]}
    inp = spec["input"]
    if hasattr(nets, "_propagate"):  # the tensor shapes, without any of the caps
        shapes = nets._propagate(spec, enforce=False)[0]
    else:
        shapes = nets.spec_tensor_shapes(spec)
    tensors = {name: torch.zeros(shape) for name, shape in shapes.items()}
    actions = spec["layers"][-1]["num_actions"]
    manifest = {
        **MANIFEST,
        "environment": dict(MANIFEST["environment"], grid=inp["height"] if grid is None else grid),
        "format": "medc-policy-bundle", "format_version": 1,
        "observation": {"channels": inp["channels"], "height": inp["height"], "width": inp["width"],
                        "channel_names": [f"c{i}" for i in range(inp["channels"])]},
        "actions": [f"a{i}" for i in range(actions)],
        "architecture": spec,
    }
    return tensors, manifest


def conv(out: int, k: int, stride: int = 1, padding: int = 0) -> dict[str, Any]:
    return {"type": "conv2d", "out_channels": out, "kernel_size": k, "stride": stride, "padding": padding}


def bomb_spec(channels: int, side: int, grow_layers: int, grow_padding: int, last: list[dict[str, Any]],
              actions: int = 8) -> dict[str, Any]:
    """The issue's compute bomb, in any size: padded 1x1 convolutions grow a small input map, then
    ``last`` (e.g. one large convolution) runs on it, then a pooling shrinks it before the heads."""
    layers = [conv(1, 1, padding=grow_padding) for _ in range(grow_layers)]
    layers += last
    layers += [{"type": "maxpool2d", "kernel_size": 64, "stride": 64, "ceil_mode": True},
               {"type": "flatten"}, {"type": "heads", "num_actions": actions}]
    return {"name": "bomb", "input": {"channels": channels, "height": side, "width": side}, "layers": layers}
