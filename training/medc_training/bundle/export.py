"""Export a policy bundle for an onboard computer: ONNX (onnxruntime, TensorRT, ...) or TorchScript
(libtorch), plus its observation/action contract as JSON beside it.

The exported graph takes ``obs`` float32 ``[batch, C, H, W]`` (the manifest's observation) and
returns ``logits`` ``[batch, A]`` and ``value`` ``[batch]``; the greedy action is
``argmax(logits)``, an index into the contract's ``actions``. A disallowed move is masked by the
caller (set its logit to -inf), as :meth:`PolicyBundle.act` does with ``mask``.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import torch

from medc_training.bundle.fileformat import BundleError
from medc_training.bundle.manifest import manifest_observation, manifest_sensing
from medc_training.bundle.policy import PolicyBundle, load_bundle

FORMATS = ("onnx", "torchscript")
#: ONNX opset of the exported graph (onnxruntime >= 1.16 runs it).
ONNX_OPSET = 17


class _Heads(torch.nn.Module):
    """The bundle's network with a plain tuple output (the exporters want tensors, not objects)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, value = self.net(obs)
        return logits, value


def contract(bundle: PolicyBundle, fmt: str, model_file: str) -> dict[str, Any]:
    """The observation and action contract of an exported ``bundle`` (what the JSON file holds)."""
    m = bundle.manifest
    obs = m["observation"]
    return {
        "format": "medc-exported-policy",
        "model_format": fmt,
        "model_file": model_file,
        "source_bundle_sha256": bundle.sha256,
        "application": m["application"],
        "environment": m["environment"],
        "sensing": manifest_sensing(m),
        "inputs": {"obs": {"dtype": "float32",
                           "shape": ["batch", obs["channels"], obs["height"], obs["width"]],
                           "observation": manifest_observation(m) or "maps",
                           "channel_names": obs["channel_names"]}},
        "outputs": {"logits": {"dtype": "float32", "shape": ["batch", len(m["actions"])]},
                    "value": {"dtype": "float32", "shape": ["batch"]}},
        "actions": m["actions"],
        "greedy_action": "argmax(logits) indexes actions; a disallowed move's logit is set to -inf first",
    }


def contract_path(out: str | os.PathLike[str]) -> Path:
    """Where :func:`export_bundle` writes the contract of model file ``out``: ``<out>.json``."""
    out = Path(out)
    return out.with_name(out.name + ".json")


def export_bundle(source: str | os.PathLike[str], out: str | os.PathLike[str], fmt: str) -> tuple[Path, Path]:
    """Write ``source``'s network to ``out`` as ``fmt`` (onnx | torchscript) and its contract to
    :func:`contract_path`; returns both paths.

    Raises:
        BundleError: ``source`` is not a valid bundle.
        ValueError: unknown format.
        ImportError: ``fmt`` is onnx and the ``onnx`` package is missing.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    bundle = load_bundle(source).to("cpu")
    model = _Heads(bundle.net).eval()
    example = torch.zeros(1, *bundle.obs_shape)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # The exporters warn about their own deprecations (TorchScript, the non-dynamo ONNX path).
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if fmt == "onnx":
            import onnx  # noqa: F401  (the exporter needs it; fail here with a clear ImportError)

            torch.onnx.export(
                model, (example,), str(out), input_names=["obs"], output_names=["logits", "value"],
                dynamic_axes={"obs": {0: "batch"}, "logits": {0: "batch"}, "value": {0: "batch"}},
                opset_version=ONNX_OPSET, dynamo=False,
            )
        else:
            traced = torch.jit.trace(model, example)
            traced.save(str(out))
    side = contract_path(out)
    side.write_text(json.dumps(contract(bundle, fmt, out.name), indent=2, sort_keys=True) + "\n")
    return out, side


__all__ = ["FORMATS", "BundleError", "contract", "contract_path", "export_bundle"]
