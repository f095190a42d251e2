"""Export a policy bundle for an onboard computer: ONNX (onnxruntime, TensorRT, ...) or TorchScript
(libtorch), plus its observation/action contract as JSON beside it.

The exported graph takes ``obs`` float32 ``[batch, C, H, W]`` (the manifest's observation) and
returns ``logits`` ``[batch, A]`` and ``value`` ``[batch]``; the greedy action is
``argmax(logits)``, an index into the contract's ``actions``. A disallowed move is masked by the
caller (set its logit to -inf), as :meth:`PolicyBundle.act` does with ``mask``.

A bundle is exported only once it passes what every agent checks (the dry run included), and the
export never writes onto its input, through a link, or over an existing file unless asked.
"""

from __future__ import annotations

import io
import json
import os
import warnings
from pathlib import Path
from typing import Any

import torch

from medc_training.bundle import policy
from medc_training.bundle.fileformat import BundleError
from medc_training.bundle.manifest import manifest_observation, manifest_sensing
from medc_training.bundle.policy import PolicyBundle, load_untrusted
from medc_training.bundle.runtime import ONNX_OPSET, Heads, onnx_bytes
from medc_training.outfiles import OutputError, check_output, is_same_file, write_output

FORMATS = ("onnx", "torchscript")


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


def export_bundle(source: str | os.PathLike[str], out: str | os.PathLike[str], fmt: str,
                  overwrite: bool = False, max_forward_s: float | None = None) -> tuple[Path, Path]:
    """Write ``source``'s network to ``out`` as ``fmt`` (onnx | torchscript) and its contract to
    :func:`contract_path`; returns both paths.

    The bundle goes through :func:`medc_training.bundle.load_untrusted` first (every static check
    and the timed dry run an agent makes, ``max_forward_s``, default the agents' limit
    ``policy.MAX_FORWARD_SECONDS``): a bundle the agents refuse is refused here with the same
    reason. Both files are checked before anything is exported
    (:func:`medc_training.outfiles.check_output`: not the input bundle, nor a link to it; not a
    folder or a device; an existing one, a link included, only with ``overwrite``) and written
    whole under a fresh temporary name moved into place (never through a link).

    Raises:
        BundleError: ``source`` is not a valid bundle, or one the agents refuse.
        OutputError: ``out`` or its contract cannot be written there (the message says why).
        ValueError: unknown format.
        ImportError: ``fmt`` is onnx and the ``onnx`` package is missing.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    targets = [check_output(path, overwrite) for path in (out, contract_path(out))]
    for target in targets:
        if is_same_file(target, source) or Path(os.path.abspath(source)) == target:
            raise OutputError(f"{target} is the bundle being exported (or a link to it): give another "
                              "file to write")
    limit = policy.MAX_FORWARD_SECONDS if max_forward_s is None else max_forward_s
    bundle = load_untrusted(source, max_forward_s=limit).to("cpu")
    if fmt == "onnx":
        import onnx  # noqa: F401  (the exporter needs it; fail here with a clear ImportError)

        data = onnx_bytes(bundle)
    else:
        buffer = io.BytesIO()
        # TorchScript warns about its own deprecation.
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            example = torch.zeros(1, *bundle.obs_shape)
            torch.jit.save(torch.jit.trace(Heads(bundle.net).eval(), example), buffer)
        data = buffer.getvalue()
    model_path, side = targets
    text = json.dumps(contract(bundle, fmt, model_path.name), indent=2, sort_keys=True) + "\n"
    write_output(model_path, data, overwrite)
    write_output(side, text.encode(), overwrite)
    return model_path, side


__all__ = ["FORMATS", "ONNX_OPSET", "BundleError", "OutputError", "contract", "contract_path",
           "export_bundle"]
