"""FedAvg: the FRL baseline's aggregation of the users' model parameters."""

from __future__ import annotations

from collections.abc import Sequence

import torch


def fedavg(state_dicts: Sequence[dict[str, torch.Tensor]], weights: Sequence[float] | None = None
           ) -> dict[str, torch.Tensor]:
    """Weighted average of parameter dicts with identical keys and shapes.

    Weights default to equal (the paper's users contribute equally); they are normalised.
    Non-float entries (e.g. integer buffers) are taken from the first user.
    """
    if not state_dicts:
        raise ValueError("fedavg needs at least one model")
    keys = list(state_dicts[0])
    for i, sd in enumerate(state_dicts[1:], start=1):
        if list(sd) != keys:
            raise ValueError(f"user {i} has parameters {sorted(set(sd) ^ set(keys))} the others lack; "
                             "FedAvg needs one architecture for all users")
        for k in keys:
            if sd[k].shape != state_dicts[0][k].shape:
                raise ValueError(f"user {i} parameter {k!r} has shape {tuple(sd[k].shape)}, "
                                 f"user 0 has {tuple(state_dicts[0][k].shape)}")
    w = torch.ones(len(state_dicts), dtype=torch.float64) if weights is None else torch.tensor(
        list(weights), dtype=torch.float64)
    if w.numel() != len(state_dicts) or (w < 0).any() or w.sum() <= 0:
        raise ValueError("fedavg weights must be one non-negative number per model, not all zero")
    w = w / w.sum()
    out = {}
    for k in keys:
        first = state_dicts[0][k]
        if not first.is_floating_point():
            out[k] = first.clone()
            continue
        acc = torch.zeros_like(first, dtype=torch.float64)
        for wi, sd in zip(w, state_dicts):
            acc += wi * sd[k].to(torch.float64)
        out[k] = acc.to(first.dtype)
    return out
