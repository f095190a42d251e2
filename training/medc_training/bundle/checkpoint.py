"""Training checkpoints without pickle: the bundle container holding arbitrary nested state
(model and optimizer state dicts, RNG states, counters); tensors are stored by flattened name,
everything else as JSON in the metadata."""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

from medc_training.bundle.fileformat import BundleError, _atomic_write, _Source

_STATE_KEY = "medc.state"


def save_state(path: str | os.PathLike[str], state: Mapping[str, Any]) -> Path:
    """Write nested training state (e.g. ``{"model": net.state_dict(), "optimizer":
    opt.state_dict(), "rng": torch.get_rng_state(), "step": 40000}``) to one safetensors file.

    Tensors and numpy arrays anywhere in the structure are stored as named tensors; dicts (any
    str/int/float/bool/None keys), lists, tuples and JSON scalars go to the metadata as JSON.
    The write is atomic (temp file + rename), so a run killed mid-save keeps its previous
    checkpoint. Read it back with ``load_state``.
    """
    tensors: dict[str, torch.Tensor] = {}
    skeleton = _encode(state, "s", tensors)
    data = _st_save(tensors, metadata={_STATE_KEY: json.dumps(skeleton)})
    target = Path(path)
    _atomic_write(target, data)
    return target


def load_state(path: str | os.PathLike[str], device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read a ``save_state`` file; tensors go to ``device`` (numpy arrays come back as numpy)."""
    with _Source(path) as src:
        data, where = src.read(0, src.size), src.where
    try:
        (header_len,) = struct.unpack("<Q", data[:8])
        header = json.loads(data[8:8 + header_len])
        skeleton = json.loads(header["__metadata__"][_STATE_KEY])
        tensors = _st_load(data)
    except Exception as exc:
        raise BundleError(f"{where}: not a training checkpoint written by save_state ({exc})") from None
    return _decode(skeleton, tensors, torch.device(device))


def _encode(obj: Any, name: str, tensors: dict[str, torch.Tensor]) -> Any:
    if isinstance(obj, torch.Tensor):
        tensors[name] = obj.detach().to("cpu").contiguous().clone()
        return {"__tensor__": name}
    if isinstance(obj, np.ndarray):
        tensors[name] = torch.from_numpy(np.ascontiguousarray(obj).copy())
        return {"__ndarray__": name}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        bad = [k for k in obj if not (k is None or isinstance(k, str | int | float | bool))]
        if bad:
            raise TypeError(f"save_state: dict keys must be str, int, float, bool or None; "
                            f"{name!r} has {bad[0]!r}")
        # JSON object keys are strings only; optimizer state is keyed by int parameter ids.
        return {"__map__": [[k, _encode(v, f"{name}.{i}", tensors)] for i, (k, v) in enumerate(obj.items())]}
    if isinstance(obj, tuple):
        return {"__tuple__": [_encode(v, f"{name}.{i}", tensors) for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_encode(v, f"{name}.{i}", tensors) for i, v in enumerate(obj)]
    if obj is None or isinstance(obj, str | int | float | bool):
        return obj
    raise TypeError(f"save_state: cannot store {type(obj).__name__} at {name!r}")


def _decode(obj: Any, tensors: dict[str, torch.Tensor], device: torch.device) -> Any:
    if isinstance(obj, dict):
        if "__tensor__" in obj:
            return tensors[obj["__tensor__"]].to(device)
        if "__ndarray__" in obj:
            return tensors[obj["__ndarray__"]].numpy()
        if "__tuple__" in obj:
            return tuple(_decode(v, tensors, device) for v in obj["__tuple__"])
        return {k: _decode(v, tensors, device) for k, v in obj["__map__"]}
    if isinstance(obj, list):
        return [_decode(v, tensors, device) for v in obj]
    return obj
