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
