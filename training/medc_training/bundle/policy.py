"""Policy bundles: saving a trained network with its manifest, and loading one back verified.

A bundle read here is untrusted data: the container is checked by
``medc_training.bundle.fileformat``, the manifest by ``medc_training.bundle.manifest``, and every
stored tensor against the shapes the declarative architecture implies, before any weight is used.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import time
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

from medc_training.bundle.dryrun import (
    TooSlow,
    dry_run_observations,
    flush_subnormal,
    scenario_key,
    timed_forward,
)
from medc_training.bundle.fileformat import (
    MANIFEST_KEY,
    BundleError,
    _atomic_write,
    _check_table,
    _parse_header,
    _Source,
)
from medc_training.bundle.manifest import complete_manifest, manifest_observation, validate_manifest
from medc_training.nets import ActorCritic, masked_logits, safe_names, spec_tensor_shapes

# The dry run of ``load_untrusted``: each of a few observations (``dryrun.dry_run_observations``)
# through the network, on this machine, must take at most this long. The shipped architectures take
# under 5 ms (61 ms for convnet-small on a 256x256 grid, first call).
MAX_FORWARD_SECONDS = 0.5
#: Refusals ``load_untrusted`` remembers: by content (sha256 of the bytes), by network (the
#: architecture, the dry run's scenario and the weights: ``network_digest``) and, for a refusal for
#: time, by structure (the architecture and the scenario: ``structure_digest``; a pass's time does not
#: depend on the weights' values, subnormals being flushed). A copy of a refused bundle that differs
#: in its bytes (a description, the order of the tensors) or, when it was too slow, in its weights is
#: refused at the cost of reading its header (and decoding its weights). A refusal for time (which a
#: busy machine can cause) is remembered for ``REFUSED_SLOW_MEMORY_S`` seconds, any other for the
#: life of the process (the oldest forgotten beyond ``MAX_REMEMBERED_REFUSALS``).
MAX_REMEMBERED_REFUSALS = 1024
REFUSED_SLOW_MEMORY_S = 600.0
#: Dry runs are rate-limited: once ``SLOW_REFUSALS_PER_WINDOW`` bundles were refused for time in the
#: last ``SLOW_WINDOW_S`` seconds (under one limit and device), a bundle whose network structure this
#: process has not accepted before is refused without a dry run until the oldest of them is that old.
#: A structure accepted before (the team's own policies) is still checked, so the pause costs an
#: attacker's variants their dry runs and the team nothing it runs.
SLOW_REFUSALS_PER_WINDOW = 3
SLOW_WINDOW_S = 60.0
MAX_ACCEPTED_STRUCTURES = 256
_REFUSED: OrderedDict[tuple[str, str, float, str], tuple[str, float]] = OrderedDict()
#: (max_forward_s, device type) -> when each recent refusal for time came (monotonic s).
_SLOW_REFUSALS: dict[tuple[float, str], list[float]] = {}
#: Structure keys whose dry run passed (newest last).
_ACCEPTED: OrderedDict[tuple[str, str, float, str], None] = OrderedDict()


def forget_refusals() -> None:
    """Forget every refusal, accepted structure and recent refusal for time this process remembers."""
    _REFUSED.clear()
    _SLOW_REFUSALS.clear()
    _ACCEPTED.clear()


def save_bundle(path: str | os.PathLike[str], net: ActorCritic, manifest: Mapping[str, Any]) -> Path:
    """Write ``net`` and ``manifest`` as one bundle file at ``path`` (atomically) and return the path.

    ``manifest`` needs ``application``; it may give ``description``, ``environment`` (the env's
    ``attributes``), ``training`` and ``metrics``. ``format``/``format_version``/``architecture``
    are filled in from ``net``; ``observation`` and ``actions`` are filled in from the net's shapes
    and the application's channel/action names (pass them explicitly to override).
    ``training.code_version`` and ``training.git_commit`` are added when absent. The complete
    manifest is validated exactly as ``load_bundle`` would, so an invalid bundle is never written.
    """
    data = bundle_bytes(net, manifest)
    target = Path(path)
    _atomic_write(target, data)
    return target


def bundle_bytes(net: ActorCritic, manifest: Mapping[str, Any]) -> bytes:
    """The bytes ``save_bundle`` would write (useful to publish without touching the disk)."""
    if not isinstance(net, ActorCritic):
        raise TypeError(f"net must be a medc_training.nets.ActorCritic, got {type(net).__name__}")
    full = complete_manifest(net, manifest)
    tensors = {name: t.detach().to("cpu", torch.float32).contiguous().clone()
               for name, t in net.state_dict().items()}
    for name, t in tensors.items():
        if not torch.isfinite(t).all():
            raise BundleError(f"refusing to save: tensor {name!r} has non-finite values")
    data = _st_save(tensors, metadata={MANIFEST_KEY: json.dumps(full, sort_keys=True)})
    with _Source(data) as src:
        src.where = "new bundle"
        _parse(src, decode=False)  # what we write must be what we accept
    return data


def allowed_logits(logits: torch.Tensor, mask: torch.Tensor | np.ndarray | None) -> torch.Tensor:
    """``logits`` [M,A] with the moves ``mask`` (bool [M,A], True = allowed; None: all) disallows set
    low (:func:`medc_training.nets.masked_logits`). ValueError for a mask of another shape."""
    if mask is None:
        return logits
    mask_t = torch.as_tensor(mask, dtype=torch.bool, device=logits.device)
    if mask_t.shape != logits.shape:
        raise ValueError(f"mask must have shape {list(logits.shape)}, got {list(mask_t.shape)}")
    return masked_logits(logits, mask_t)


@dataclass(frozen=True)
class PolicyBundle:
    """A loaded, verified bundle: its manifest and the rebuilt network (in eval mode)."""

    manifest: dict[str, Any]
    net: ActorCritic
    sha256: str

    @property
    def application(self) -> str:
        return self.manifest["application"]

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        return self.net.obs_shape

    @property
    def num_actions(self) -> int:
        return self.net.num_actions

    @property
    def observation(self) -> str | None:
        """The observation variant the model takes (target localization; 'maps' when the manifest
        predates variants), or None for the other applications."""
        return manifest_observation(self.manifest)

    @property
    def action_names(self) -> list[str]:
        return list(self.manifest["actions"])

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def to(self, device: torch.device | str) -> PolicyBundle:
        """The same policy on ``device`` (a new bundle object; this one is unchanged)."""
        net = ActorCritic(self.net.spec, initialize=False)
        net.load_state_dict(self.net.state_dict())
        return PolicyBundle(self.manifest, net.to(device).eval(), self.sha256)

    def _logits(self, obs: torch.Tensor | np.ndarray, mask: torch.Tensor | np.ndarray | None) -> torch.Tensor:
        device = self.device
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=device)
        with torch.no_grad():
            logits, _ = self.net(obs_t)
        return allowed_logits(logits, mask)

    def action_probs(self, obs: torch.Tensor | np.ndarray, mask: torch.Tensor | np.ndarray | None = None
                     ) -> torch.Tensor:
        """Action probabilities ``[M, A]`` for observations ``[M, C, H, W]``; disallowed moves get 0."""
        return torch.softmax(self._logits(obs, mask), dim=-1)

    def act(self, obs: torch.Tensor | np.ndarray, mask: torch.Tensor | np.ndarray | None = None,
            greedy: bool = True, generator: torch.Generator | None = None) -> torch.Tensor:
        """Actions int64 ``[M]``: the most probable allowed move, or a sample when ``greedy=False``."""
        logits = self._logits(obs, mask)
        if greedy:
            return logits.argmax(dim=-1)
        return torch.multinomial(torch.softmax(logits, dim=-1), 1, generator=generator).squeeze(-1)


def load_bundle(source: str | os.PathLike[str] | bytes | bytearray | memoryview,
                device: torch.device | str = "cpu") -> PolicyBundle:
    """Load and verify a bundle from a path or from its bytes; the net is on ``device`` in eval mode.

    Subnormal weights (below ~1.2e-38, a compute bomb on CPUs that handle them slowly) are loaded
    as 0 (``dryrun.flush_subnormal``); ``sha256`` is still that of the bytes as stored.

    Raises ``BundleError`` for anything that is not a valid bundle (see the module docstring);
    no other exception escapes for any file content (a loader failure, a RecursionError or a
    MemoryError included, is reported as a BundleError).
    """
    with _Source(source) as src:
        return _load(src, device)


def _load(src: _Source, device: torch.device | str) -> PolicyBundle:
    try:
        manifest, tensors, data = _parse(src, decode=True)
        net = ActorCritic(manifest["architecture"], initialize=False)  # every weight is overwritten
        net.load_state_dict(tensors, strict=True)
        return PolicyBundle(manifest, net.to(device).eval(), hashlib.sha256(data).hexdigest())
    except BundleError:
        raise
    except Exception as exc:  # no file may end in anything but a BundleError
        raise BundleError(f"{src.where}: cannot be loaded ({type(exc).__name__} in the loader)") from exc


def read_manifest(source: str | os.PathLike[str] | bytes | bytearray | memoryview) -> dict[str, Any]:
    """The validated manifest of a bundle (header, manifest and tensor table checked; weights not decoded).

    A file is read only up to the end of its header: the weights are never read.
    """
    with _Source(source) as src:
        try:
            return _parse(src, decode=False)[0]
        except BundleError:
            raise
        except Exception as exc:
            raise BundleError(f"{src.where}: cannot be loaded ({type(exc).__name__} in the loader)") from exc


def load_untrusted(source: str | os.PathLike[str] | bytes | bytearray | memoryview,
                   device: torch.device | str = "cpu",
                   max_forward_s: float = MAX_FORWARD_SECONDS) -> PolicyBundle:
    """``load_bundle`` plus a timed dry run: what every node does with a bundle from the graph.

    The agent nodes (before swapping policies) and the registry bridge (before caching and handing
    out a fetched bundle) both call this, so a bundle one accepts the other accepts too. After
    every static check of ``load_bundle`` (including the architecture's compute and memory caps,
    ``nets.MAX_OPERATIONS`` and ``nets.MAX_ACTIVATION_BYTES``), each observation of
    ``dryrun.dry_run_observations`` (a blank one, one the application's environment makes for the
    manifest's scenario, a dense random one) goes through the network with every move allowed and
    flush-to-zero on; a bundle whose pass on any of them takes longer than ``max_forward_s`` seconds
    is refused, and the pass is abandoned as soon as it is over (or a large layer's estimate puts it
    over: ``dryrun.timed_forward``), so refusing a slow bundle costs about ``max_forward_s``.

    A refusal after the header checks is remembered (``_REFUSED``): the same bytes under any name,
    the same network in other bytes, and for a refusal for time the same structure with any weights,
    are refused at once with the same reason; dry runs of new structures are rate-limited
    (``SLOW_REFUSALS_PER_WINDOW``).

    Raises:
        BundleError: for any refusal; no other exception escapes.
    """
    with _Source(source) as src:
        where = src.where
        try:
            manifest = _parse(src, decode=False)[0]  # header, manifest and table first: bounded reads
            data = src.read(0, src.size)
        except BundleError:
            raise
        except Exception as exc:
            raise BundleError(f"{where}: cannot be loaded ({type(exc).__name__} in the loader)") from exc
    run = (float(max_forward_s), torch.device(device).type)
    content = ("content", hashlib.sha256(data).hexdigest(), *run)
    structure = ("network structure", structure_digest(manifest), *run)
    _refuse_if_remembered(where, content, structure)
    _refuse_if_paused(where, structure)
    try:
        with _Source(data) as src:
            src.where = where
            bundle = _load(src, device)
    except BundleError as exc:
        _remember(exc, where, content)
        raise
    network = ("network", network_digest(bundle), *run)
    _refuse_if_remembered(where, network)
    try:
        _dry_run(bundle, where, max_forward_s)
    except BundleError as exc:
        _remember(exc, where, content, network, structure)
        raise
    _ACCEPTED[structure] = None
    _ACCEPTED.move_to_end(structure)
    while len(_ACCEPTED) > MAX_ACCEPTED_STRUCTURES:
        _ACCEPTED.popitem(last=False)
    return bundle


def structure_digest(manifest: Mapping[str, Any]) -> str:
    """Hex sha256 of what a dry run's time depends on: the architecture and the scenario its
    environment observation is made in (``dryrun.scenario_key``)."""
    what = {"architecture": manifest.get("architecture"), "scenario": list(scenario_key(manifest))}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()


def network_digest(bundle: PolicyBundle) -> str:
    """Hex sha256 of the network: its structure digest and its weights as loaded (by name)."""
    digest = hashlib.sha256(structure_digest(bundle.manifest).encode())
    for name, tensor in sorted(bundle.net.state_dict().items()):
        t = tensor.detach().to("cpu", torch.float32).contiguous()
        digest.update(f"\0{name}\0{list(t.shape)}\0".encode())
        digest.update(t.numpy().tobytes())
    return digest.hexdigest()


def _refuse_if_remembered(where: str, *keys: tuple[str, str, float, str]) -> None:
    for key in keys:
        remembered = _remembered_refusal(key)
        if remembered is not None:
            raise BundleError(f"{where}: {remembered} (the same {key[0]} was refused before; not "
                              "checked again)")


def _refuse_if_paused(where: str, structure: tuple[str, str, float, str]) -> None:
    now = time.monotonic()
    recent = [t for t in _SLOW_REFUSALS.get(structure[2:], []) if now - t < SLOW_WINDOW_S]
    _SLOW_REFUSALS[structure[2:]] = recent
    if len(recent) >= SLOW_REFUSALS_PER_WINDOW and structure not in _ACCEPTED:
        wait = SLOW_WINDOW_S - (now - recent[-SLOW_REFUSALS_PER_WINDOW])
        raise BundleError(f"{where}: not checked: {len(recent)} bundles were too slow to act with in the "
                          f"last {SLOW_WINDOW_S:g} s, so dry runs of a network structure not accepted "
                          f"before are paused for {wait:.0f} s")


def _remember(exc: BundleError, where: str, content, network=None, structure=None) -> None:
    """Remember the refusal ``exc`` under ``content`` and ``network``, and under ``structure`` when
    it was for time; a refusal for memory is the machine's state, not the bundle's: not remembered."""
    if isinstance(exc.__cause__, MemoryError):
        return
    text = str(exc)
    reason = text[len(where) + 2:] if text.startswith(f"{where}: ") else text
    slow = isinstance(exc.__cause__, TooSlow)
    for key in (content, network, structure if slow else None):
        if key is not None:
            _remember_refusal(key, reason, slow)
    if slow:
        _SLOW_REFUSALS.setdefault(content[2:], []).append(time.monotonic())


def _dry_run(bundle: PolicyBundle, where: str, max_forward_s: float) -> None:
    allowed = torch.ones((1, bundle.num_actions), dtype=torch.bool, device=bundle.device)
    what = ("a blank observation", "an observation of its environment", "a random observation")
    observations = dry_run_observations(bundle.manifest, bundle.obs_shape)
    for i, obs in enumerate(observations):
        name = what[0] if i == 0 else what[-1] if i == len(observations) - 1 else what[1]
        try:
            timed_forward(bundle.net, obs.to(bundle.device), allowed, max_forward_s)
        except TooSlow as slow:
            about = "about " if slow.estimated else ""
            how = f"{name}, estimated from a part of layer {slow.layer}" if slow.estimated else name
            raise BundleError(f"{where}: one observation takes {about}{slow.seconds:.2f} s to evaluate, "
                              f"over the {max_forward_s:g} s limit (too slow to act with: {how})") from slow
        except Exception as exc:
            raise BundleError(f"{where}: fails on {name} ({type(exc).__name__})") from exc


def _remembered_refusal(key: tuple[str, str, float, str]) -> str | None:
    entry = _REFUSED.get(key)
    if entry is None:
        return None
    reason, expires = entry
    if time.monotonic() > expires:
        del _REFUSED[key]
        return None
    _REFUSED.move_to_end(key)
    return reason


def _remember_refusal(key: tuple[str, str, float, str], reason: str, slow: bool) -> None:
    _REFUSED[key] = (reason, time.monotonic() + REFUSED_SLOW_MEMORY_S if slow else math.inf)
    _REFUSED.move_to_end(key)
    while len(_REFUSED) > MAX_REMEMBERED_REFUSALS:
        _REFUSED.popitem(last=False)


def dry_run_seconds(bundle: PolicyBundle, obs: torch.Tensor | None = None) -> float:
    """Wall time of one greedy decision on ``obs`` [1,C,H,W] (default a blank observation) with
    every move allowed and flush-to-zero on (no limit)."""
    if obs is None:
        obs = torch.zeros((1, *bundle.obs_shape), device=bundle.device)
    allowed = torch.ones((obs.shape[0], bundle.num_actions), dtype=torch.bool, device=bundle.device)
    return timed_forward(bundle.net, obs.to(bundle.device), allowed, math.inf)


def bundle_digest(source: str | os.PathLike[str] | bytes | bytearray | memoryview) -> str:
    """Hex sha256 of the bundle's bytes (no validation): a content address independent of IPFS."""
    with _Source(source) as src:
        digest = hashlib.sha256()
        for offset in range(0, src.size, 1 << 20):
            digest.update(src.read(offset, min(1 << 20, src.size - offset)))
        return digest.hexdigest()


def _parse(src: _Source, decode: bool) -> tuple[dict[str, Any], dict[str, torch.Tensor], bytes]:
    """(validated manifest, tensors, all bytes); tensors and bytes only with ``decode``."""
    where = src.where
    raw_manifest, table, start = _parse_header(src)
    _check_table(table, src.size - start, where)
    try:
        manifest = validate_manifest(raw_manifest)
    except BundleError as exc:
        raise BundleError(f"{where}: {exc}") from None
    expected = spec_tensor_shapes(manifest["architecture"])
    missing = sorted(set(expected) - set(table))
    extra = sorted(set(table) - set(expected))
    if missing:
        raise BundleError(f"{where}: missing tensors {safe_names(missing)} required by the architecture")
    if extra:
        raise BundleError(f"{where}: unexpected tensors {safe_names(extra)} not in the architecture")
    for name, shape in expected.items():
        stored = tuple(table[name]["shape"])
        if stored != shape:
            raise BundleError(f"{where}: tensor {name!r} has shape {list(stored)}, the architecture "
                              f"needs {list(shape)}")
    if not decode:
        return manifest, {}, b""
    data = src.read(0, src.size)  # only now, with the header and table vetted and the sizes known
    if len(data) < start or struct.unpack("<Q", data[:8])[0] != start - 8:
        raise BundleError(f"{where}: the file changed while it was read")
    try:
        tensors = _st_load(data)
    except Exception as exc:  # safetensors' own error types
        raise BundleError(f"{where}: cannot decode tensors ({type(exc).__name__})") from None
    if set(tensors) != set(expected) or any(tuple(t.shape) != expected[n] for n, t in tensors.items()):
        raise BundleError(f"{where}: the file changed while it was read")
    for name, tensor in tensors.items():
        if not torch.isfinite(tensor).all():
            raise BundleError(f"{where}: tensor {name!r} contains NaN or infinite values")
        flush_subnormal(tensor)
    return manifest, tensors, data
