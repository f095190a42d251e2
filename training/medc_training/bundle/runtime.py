"""Running a loaded bundle's network for an agent's decisions: onnxruntime, or PyTorch.

An agent node decides one move at a time. At batch 1 a small network spends most of its time in
PyTorch's per-operator dispatch rather than in arithmetic (the window-9 convolutional team: about
0.13 ms a forward pass in PyTorch, 0.03 ms in onnxruntime, on one core of the 2-core machine;
``medc-radbench --cost`` measures the whole decision). :func:`decider` gives a bundle's
:class:`Decider`, which runs the network in one of:

* ``onnxruntime``: the network this process rebuilt from the bundle's weights (after every check of
  :func:`~medc_training.bundle.load_untrusted`) is exported to ONNX in memory by PyTorch's exporter
  and run by an onnxruntime session of one thread, on the calling thread under
  :func:`~medc_training.bundle.flush_denormals` as the PyTorch path (the mode restored after).
  onnxruntime only ever reads a graph made here, never bytes from the file. Before it is used,
  its logits and values on the dry run's observations
  (:func:`~medc_training.bundle.dry_run_observations`: blank, environment-made, dense random) must
  equal PyTorch's within :data:`ATOL`; a greedy choice can then differ from PyTorch's only where
  two allowed moves' logits are closer than that;
* ``torch``: :meth:`PolicyBundle.act`'s own computation.

``auto`` (the default of the agent nodes) takes onnxruntime where it is installed and passes that
check, else PyTorch, and says which and why (:attr:`Decider.note`).
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
import warnings
from typing import Any

import numpy as np
import torch

from medc_training.bundle.dryrun import dry_run_observations, flush_denormals
from medc_training.bundle.policy import PolicyBundle, allowed_logits

__all__ = ["ATOL", "ONNX_OPSET", "RUNTIMES", "Decider", "Heads", "RuntimeUnavailable", "decider",
           "onnx_bytes"]

#: The runtimes a decider can run a network in; ``auto`` picks (module docstring).
RUNTIMES = ("auto", "onnxruntime", "torch")
#: Largest difference from PyTorch's logits and values onnxruntime may make on the probe
#: observations (float32 rounding of a few hundred thousand multiply-accumulates is about 1e-5).
ATOL = 1e-4
#: ONNX opset of the exported graphs, in memory and in files (onnxruntime >= 1.16 runs it).
ONNX_OPSET = 17


class RuntimeUnavailable(RuntimeError):
    """The runtime asked for cannot run this bundle here; the message says why and what to do."""


class Heads(torch.nn.Module):
    """The bundle's network with a plain tuple output (the exporters want tensors, not objects)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, value = self.net(obs)
        return logits, value


def onnx_bytes(bundle: PolicyBundle) -> bytes:
    """``bundle``'s network as an ONNX model (input ``obs`` float32 [batch,C,H,W]; outputs
    ``logits`` [batch,A] and ``value`` [batch]), exported from the network this process built."""
    model = Heads(bundle.net).eval()
    example = torch.zeros(1, *bundle.obs_shape, device=bundle.device)
    buffer = io.BytesIO()
    # The exporter warns about its own deprecations (the non-dynamo path).
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model, (example,), buffer, input_names=["obs"], output_names=["logits", "value"],
            dynamic_axes={"obs": {0: "batch"}, "logits": {0: "batch"}, "value": {0: "batch"}},
            opset_version=ONNX_OPSET, dynamo=False,
        )
    return buffer.getvalue()


class Decider:
    """Greedy moves of one bundle in one runtime (:func:`decider` makes one).

    ``runtime``: ``onnxruntime`` or ``torch``, the one it runs in; ``note``: why ``auto`` took PyTorch
    (None otherwise); ``bundle``: the policy.
    """

    def __init__(self, bundle: PolicyBundle, runtime: str, session: Any = None,
                 note: str | None = None) -> None:
        self.bundle, self.runtime, self.note = bundle, runtime, note
        self._session = session

    def heads(self, obs: torch.Tensor | np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(logits [M,A], value [M]) for observations [M,C,H,W], on the CPU."""
        if self._session is None:
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.bundle.device)
            with torch.no_grad(), flush_denormals():
                logits, value = self.bundle.net(obs_t)
            return logits, value
        array = obs.detach().cpu().numpy() if isinstance(obs, torch.Tensor) else np.asarray(obs)
        # One intra-op thread: the session runs on this thread, under its flush-to-zero mode.
        with flush_denormals():
            logits, value = self._session.run(None, {"obs": np.ascontiguousarray(array, dtype=np.float32)})
        return torch.from_numpy(logits), torch.from_numpy(value)

    def act(self, obs: torch.Tensor | np.ndarray,
            mask: torch.Tensor | np.ndarray | None = None) -> torch.Tensor:
        """Actions int64 [M]: the most probable allowed move (``mask`` bool [M,A], True = allowed),
        as :meth:`PolicyBundle.act` with ``greedy=True`` chooses."""
        return allowed_logits(self.heads(obs)[0], mask).argmax(dim=-1)


def _import_onnxruntime() -> Any:
    """``import onnxruntime``, leaving no file behind: its telemetry library writes a session file
    (``.ses``) into the temporary folder when the module is first imported, so the import runs with
    ``TMPDIR`` pointed at a private folder removed right after (the process's own temporary folder,
    which ``tempfile`` has already read, is unchanged); its telemetry events are switched off."""
    if "onnxruntime" in sys.modules:
        module = sys.modules["onnxruntime"]
        if module is None:
            raise ImportError("onnxruntime is blocked in this process")
        return module
    with tempfile.TemporaryDirectory(prefix="medc-onnxruntime-") as private:
        before = os.environ.get("TMPDIR")
        os.environ["TMPDIR"] = private
        try:
            import onnxruntime
        finally:
            if before is None:
                os.environ.pop("TMPDIR", None)
            else:
                os.environ["TMPDIR"] = before
    onnxruntime.disable_telemetry_events()
    return onnxruntime


def _session(bundle: PolicyBundle) -> Any:
    """An onnxruntime session of ``bundle``'s network that agrees with PyTorch on the probe
    observations; RuntimeUnavailable saying why not."""
    try:
        ort = _import_onnxruntime()
    except ImportError as exc:
        raise RuntimeUnavailable("onnxruntime is not installed (pip install -r requirements.txt); "
                                 "or run the policy in PyTorch (runtime 'torch')") from exc
    if bundle.device.type != "cpu":
        raise RuntimeUnavailable(f"the bundle is on {bundle.device}; onnxruntime runs it on the CPU here")
    try:
        model = onnx_bytes(bundle)
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3
        session = ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # an exporter or runtime failure: the PyTorch path still runs the policy
        raise RuntimeUnavailable(f"the network could not be run in onnxruntime ({type(exc).__name__}); "
                                 "run it in PyTorch (runtime 'torch')") from exc
    probe = Decider(bundle, "onnxruntime", session)
    reference = Decider(bundle, "torch")
    for obs in dry_run_observations(bundle.manifest, bundle.obs_shape):
        for got, want, what in zip(probe.heads(obs), reference.heads(obs), ("logits", "values")):
            gap = float((got - want).abs().max())
            if not gap <= ATOL:  # NaN included
                raise RuntimeUnavailable(f"onnxruntime's {what} differ from PyTorch's by {gap:.2g} "
                                         f"(more than {ATOL:g}) on a probe observation; run the policy in "
                                         "PyTorch (runtime 'torch')")
    return session


def decider(bundle: PolicyBundle, runtime: str = "auto") -> Decider:
    """The :class:`Decider` of ``bundle`` in ``runtime`` (one of :data:`RUNTIMES`; module docstring).

    Raises:
        ValueError: an unknown runtime.
        RuntimeUnavailable: ``onnxruntime`` was asked for and cannot run this bundle here (``auto``
        falls back to PyTorch instead, saying why in :attr:`Decider.note`).
    """
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime must be one of {', '.join(RUNTIMES)}, got {str(runtime)[:40]!r}")
    if runtime == "torch":
        return Decider(bundle, "torch")
    try:
        return Decider(bundle, "onnxruntime", _session(bundle))
    except RuntimeUnavailable as exc:
        if runtime == "onnxruntime":
            raise
        return Decider(bundle, "torch", note=str(exc))
