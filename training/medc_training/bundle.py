"""Policy bundles: one safetensors file holding a trained policy and its JSON manifest.

A bundle is a plain safetensors file (readable by any safetensors tool). Its tensors are the
actor-critic's parameters (float32, named as in ``medc_training.nets``); its metadata holds one
entry, ``"medc.manifest"``, a JSON object:

.. code-block:: text

    format            "medc-policy-bundle"
    format_version    1
    application       one of KNOWN_APPLICATIONS ("target_localization", ...)
    description       optional free text (what the registry shows)
    environment       {attribute: number | bool | string}, e.g. {"agents": 3, "walls": 2, "grid": 30}
    observation       {"channels": C, "height": H, "width": W, "channel_names": [C names],
                       "name": variant}; "name" is the observation variant the model takes
                       (target localization: "maps", "maps+estimate", "egoR", "egoR+estimate",
                       see medc_training.envs.tl_observation); a bundle without it takes "maps"
    actions           [A action names], e.g. ["N", "NE", "E", "SE", "S", "SW", "W", "NW"]
    architecture      the declarative network spec (medc_training.nets), input C x H x W, A actions
    training          {"method", "steps", "seed", "code_version", "git_commit", ...}
    metrics           {name: number | string | bool | null}, e.g. {"mean_episode_length": 23.4}

One file means one IPFS CID: the registry stores and verifies exactly these bytes.

Loading treats a bundle as untrusted data: the header is parsed and checked here before any tensor
is decoded; nothing is unpickled and no code from the file runs; the network is rebuilt from the
declarative spec and every stored tensor is checked against the shapes that spec implies. Anything
wrong raises ``BundleError`` with a message saying what is wrong.

Training checkpoints (``save_state`` / ``load_state``) reuse the same container for arbitrary nested
state (model and optimizer state dicts, RNG states, counters) without pickle: tensors are stored by
flattened name, everything else as JSON in the metadata.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import math
import os
import re
import stat
import struct
import subprocess
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load as _st_load
from safetensors.torch import save as _st_save

import medc_training
from medc_training.envs import ENV_NAMES
from medc_training.nets import (
    ActorCritic,
    SpecError,
    masked_logits,
    safe_names,
    safe_repr,
    spec_tensor_shapes,
    validate_spec,
)

FORMAT = "medc-policy-bundle"
FORMAT_VERSION = 1
MANIFEST_KEY = "medc.manifest"

# A bundle for an application this code does not know cannot be run by it, so it is rejected
# rather than guessed at.
KNOWN_APPLICATIONS: tuple[str, ...] = tuple(ENV_NAMES)

MAX_HEADER_BYTES = 1 << 20  # the manifest and tensor table of any sane bundle fit easily in 1 MiB
MAX_BUNDLE_BYTES = 512 << 20
# Limits on the JSON of the header and of the manifest, checked before and while parsing it. The
# shipped bundles' manifests are under 2 KB, nest 4 levels deep and hold no string over 120
# characters; a 256-layer architecture needs ~25 KB.
MAX_JSON_DEPTH = 16  # nested objects/lists; checked by a scan before json.loads ever recurses
MAX_MANIFEST_CHARS = 64 << 10
MAX_STRING_CHARS = 4096  # any key or string value
MAX_NUMBER_CHARS = 40  # any JSON number literal (a 64-bit seed has 20 digits)
# The dry run of ``load_untrusted``: one blank observation through the network, on this machine.
# The shipped architectures take under 5 ms (61 ms for convnet-small on a 256x256 grid, first call).
MAX_FORWARD_SECONDS = 0.5
_MANIFEST_KEYS = {
    "format", "format_version", "application", "description", "environment", "observation",
    "actions", "architecture", "training", "metrics",
}
_DTYPE_SIZES = {"F32": 4}


class BundleError(ValueError):
    """The file or bytes are not a valid MEDC policy bundle; the message says what is wrong."""


# ---------------------------------------------------------------------------------------------
# Saving


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


def complete_manifest(net: ActorCritic, manifest: Mapping[str, Any]) -> dict[str, Any]:
    """``manifest`` with the format, architecture, observation, actions and provenance filled in."""
    if not isinstance(manifest, Mapping):
        raise BundleError(f"manifest must be a dict, got {type(manifest).__name__}")
    unknown = sorted(set(manifest) - _MANIFEST_KEYS, key=str)
    if unknown:
        raise BundleError(f"manifest: unknown keys {safe_names(unknown)}; allowed: {sorted(_MANIFEST_KEYS)}")
    try:
        full: dict[str, Any] = json.loads(json.dumps(dict(manifest)))  # deep copy; proves JSON-able
    except (TypeError, ValueError) as exc:
        raise BundleError(f"manifest must hold JSON values only (str, int, float, bool, None, lists, "
                          f"dicts): {exc}") from None
    app = full.get("application")
    c, h, w = net.obs_shape
    default_channels, default_actions = _env_names(app)
    full["format"] = FORMAT
    full["format_version"] = FORMAT_VERSION
    full["architecture"] = net.spec
    obs = dict(full.get("observation") or {})
    if app == "target_localization":
        spec = _observation_spec(obs.get("name", "maps"))
        obs["name"] = spec.name
        obs.setdefault("channel_names", list(spec.channels))
    elif obs.get("name", "maps") != "maps" and default_channels is not None:
        # An agent-centred window (fleet, maze): channel 0 marks the cells off the grid.
        default_channels = ["off_grid", *default_channels[1:]]
    obs.setdefault("channels", c)
    obs.setdefault("height", h)
    obs.setdefault("width", w)
    if default_channels is None or len(default_channels) != c:
        default_channels = [f"channel_{i}" for i in range(c)]
    obs.setdefault("channel_names", default_channels)
    full["observation"] = obs
    if default_actions is None or len(default_actions) != net.num_actions:
        default_actions = [f"action_{i}" for i in range(net.num_actions)]
    full.setdefault("actions", default_actions)
    full.setdefault("environment", {})
    # A metric that was not measured (NaN) is stored as null: strict JSON has no NaN.
    metrics = full.setdefault("metrics", {})
    if isinstance(metrics, dict):
        full["metrics"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                           for k, v in metrics.items()}
    training = dict(full.get("training") or {})
    training.setdefault("code_version", medc_training.__version__)
    if "git_commit" not in training:
        training["git_commit"] = _git_commit()
    full["training"] = training
    return validate_manifest(full)


def manifest_observation(manifest: Mapping[str, Any]) -> str | None:
    """The observation variant a validated manifest's model takes: its ``observation.name``; for
    target localization 'maps' when the manifest predates variants; None for another
    application's manifest without a name (its absolute maps)."""
    name = manifest["observation"].get("name")
    if name is None and manifest.get("application") == "target_localization":
        return "maps"
    return None if name is None else str(name)


def manifest_sensing(manifest: Mapping[str, Any]) -> str:
    """The sensing preset a validated target-localization manifest's model was trained under: its
    ``environment.sensing`` (the core records it when it is not the default), 'paper-simple' when
    the manifest names none (every bundle made before the presets).

    Raises:
        BundleError: ``environment.sensing`` is not the name of a preset
        (:data:`medc_training.envs.tl_sensing.SENSING_PRESETS`).
    """
    from medc_training.envs.tl_sensing import DEFAULT_SENSING, SENSING_PRESETS

    name = (manifest.get("environment") or {}).get("sensing", DEFAULT_SENSING)
    if not isinstance(name, str) or name not in SENSING_PRESETS:
        raise BundleError(f"manifest: environment.sensing is {safe_repr(name)}, not one of "
                          f"{', '.join(sorted(SENSING_PRESETS))}")
    return name


def check_sensing(manifest: Mapping[str, Any], sensing: str, what: str = "this bundle") -> None:
    """Refuse a target-localization bundle trained under another sensing preset than ``sensing``
    (the team's). Raises BundleError naming both presets; ``what`` names the bundle in it."""
    from medc_training.envs.tl_sensing import parse_sensing

    mine = manifest_sensing(manifest)
    team = parse_sensing(sensing).name
    if mine != team:
        raise BundleError(
            f"{what} was trained under the sensing model {mine!r}, but this team senses with {team!r}; "
            f"use a bundle trained with sensing {team!r} (environment.sensing in its manifest; none "
            f"means 'paper-simple'), or run the team with sensing {mine!r}"
        )


def _grid_task_side(name: Any, grid: int) -> int:
    """Side of a fleet-coordination / maze-cleaning observation: 'maps' (G) or 'egoR' (2R+1)."""
    from medc_training.envs.observation import parse_observation

    try:
        spec = parse_observation(name)
    except ValueError:  # its message holds the name: do not echo it
        spec = None
    if spec is None or spec.estimate:
        raise BundleError("manifest: observation.name must be 'maps' or 'egoR' for this application")
    return spec.side(grid)


def _observation_spec(name: Any):
    from medc_training.envs.observation import parse_observation

    try:
        return parse_observation(name)
    except ValueError:
        raise BundleError("manifest: observation.name is not an observation variant this code knows "
                          "(maps, maps+estimate, egoR, egoR+estimate)") from None


def _env_names(app: Any) -> tuple[list[str] | None, list[str] | None]:
    """The application's observation channel and action names, from its environment module.

    Each environment module ``medc_training.envs.<application>`` may define ``CHANNELS`` and
    ``ACTION_NAMES``; the environment is the single source of truth for what its indices mean.
    """
    if app not in KNOWN_APPLICATIONS:
        return None, None  # validate_manifest reports the unknown application
    try:
        module = importlib.import_module(f"medc_training.envs.{app}")
    except ModuleNotFoundError:
        return None, None
    channels = getattr(module, "CHANNELS", None)
    actions = getattr(module, "ACTION_NAMES", None)
    return (list(channels) if channels else None), (list(actions) if actions else None)


def _git_commit() -> str | None:
    """HEAD of the repository this code runs from, or None when it is not a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
            capture_output=True, text=True, timeout=5, check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and len(commit) == 40 else None


def _atomic_write(target: Path, data: bytes) -> None:
    # A killed writer must never leave a half-written model where a reader (or resume) looks.
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# ---------------------------------------------------------------------------------------------
# Manifest validation


def _is_scalar(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    return value is None or isinstance(value, str | int | bool)


def _check_int(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise BundleError(f"manifest: {what} must be a positive integer, got {safe_repr(value)}")
    return value


def _check_names(value: Any, count: int, what: str) -> None:
    if not isinstance(value, list) or not all(isinstance(n, str) and n for n in value):
        raise BundleError(f"manifest: {what} must be a list of non-empty strings")
    if len(value) != count:
        raise BundleError(f"manifest: {what} lists {len(value)} names but the network has {count}")
    if len(set(value)) != len(value):
        raise BundleError(f"manifest: {what} has duplicate names")


def validate_manifest(manifest: Any) -> dict[str, Any]:
    """Check a complete manifest (as stored in a bundle); return it with a normalised architecture.

    Cross-checks the claims against each other: the observation shape and the action count must
    be the architecture's, a ``grid`` environment attribute must match the observation's size, and
    the application must be one this code knows.
    """
    if not isinstance(manifest, dict):
        raise BundleError(f"manifest must be a JSON object, got {type(manifest).__name__}")
    unknown = sorted(set(manifest) - _MANIFEST_KEYS, key=str)
    if unknown:
        raise BundleError(f"manifest: unknown keys {safe_names(unknown)}; allowed: {sorted(_MANIFEST_KEYS)}")
    missing = sorted(_MANIFEST_KEYS - {"description"} - set(manifest))
    if missing:
        raise BundleError(f"manifest: missing keys {missing}")
    if manifest["format"] != FORMAT:
        raise BundleError(f"manifest: format is {safe_repr(manifest['format'])}, expected {FORMAT!r}")
    version = manifest["format_version"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise BundleError(f"manifest: format_version must be an integer, got {safe_repr(version)}")
    if version != FORMAT_VERSION:
        newer = " (written by a newer medc_training; upgrade to load it)" if version > FORMAT_VERSION else ""
        raise BundleError(f"manifest: format_version {version} is not supported, expected "
                          f"{FORMAT_VERSION}{newer}")
    app = manifest["application"]
    if app not in KNOWN_APPLICATIONS:
        raise BundleError(f"manifest: unknown application {safe_repr(app)}; known: "
                          f"{', '.join(KNOWN_APPLICATIONS)}")
    if "description" in manifest and not isinstance(manifest["description"], str):
        raise BundleError("manifest: description must be a string")
    for section in ("environment", "training", "metrics"):
        value = manifest[section]
        if not isinstance(value, dict):
            raise BundleError(f"manifest: {section} must be an object, got {type(value).__name__}")
        # Environment attributes feed the registry's distance D_m; they must be flat scalars.
        flat = section == "environment"
        for key, item in value.items():
            if flat and not _is_scalar(item):
                raise BundleError(f"manifest: environment.{safe_repr(key)[1:-1]} must be a finite number, "
                                  f"bool or string, got {safe_repr(item)}")
            if section == "metrics" and not _is_scalar(item):
                raise BundleError(f"manifest: metrics.{safe_repr(key)[1:-1]} must be a finite number, bool, "
                                  "string or null")
    try:
        spec = validate_spec(manifest["architecture"])
    except SpecError as exc:
        raise BundleError(f"manifest: invalid architecture: {exc}") from None
    obs = manifest["observation"]
    keys = {"channels", "height", "width", "channel_names"}
    if not isinstance(obs, dict) or not keys <= set(obs) <= keys | {"name"}:
        raise BundleError("manifest: observation must be {channels, height, width, channel_names[, name]}")
    shape = tuple(_check_int(obs[k], f"observation.{k}") for k in ("channels", "height", "width"))
    net_shape = (spec["input"]["channels"], spec["input"]["height"], spec["input"]["width"])
    if shape != net_shape:
        raise BundleError(f"manifest: observation shape {list(shape)} does not match the architecture's "
                          f"input {list(net_shape)}")
    _check_names(obs["channel_names"], shape[0], "observation.channel_names")
    num_actions = spec["layers"][-1]["num_actions"]
    _check_names(manifest["actions"], num_actions, "actions")
    grid = manifest["environment"].get("grid")
    name = obs.get("name")
    has_grid = isinstance(grid, int) and not isinstance(grid, bool)
    if name is not None and app == "target_localization":
        ospec = _observation_spec(name)
        if list(obs["channel_names"]) != list(ospec.channels):
            raise BundleError(f"manifest: observation {ospec.name} has channels {list(ospec.channels)}, "
                              "but channel_names differ")
        if has_grid and ospec.shape(grid) != shape:
            raise BundleError(f"manifest: environment.grid is {safe_repr(grid)} but the observation is "
                              f"{shape[1]}x{shape[2]} with {shape[0]} channels; "
                              f"{ospec.name} on that grid is {list(ospec.shape(grid))}")
    elif name is not None:
        side = _grid_task_side(name, grid if has_grid else shape[1])
        if (shape[1], shape[2]) != (side, side):
            raise BundleError(f"manifest: observation {safe_repr(name)} is {side}x{side} here, but the "
                              f"bundle declares {shape[1]}x{shape[2]}")
    elif grid is not None and (grid != shape[1] or grid != shape[2]):
        raise BundleError(f"manifest: environment.grid is {safe_repr(grid)} but the observation is "
                          f"{shape[1]}x{shape[2]}")
    out = dict(manifest)
    out["architecture"] = spec
    return out


# ---------------------------------------------------------------------------------------------
# Loading


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
        if mask is not None:
            mask_t = torch.as_tensor(mask, dtype=torch.bool, device=device)
            if mask_t.shape != logits.shape:
                raise ValueError(f"mask must have shape {list(logits.shape)}, got {list(mask_t.shape)}")
            logits = masked_logits(logits, mask_t)
        return logits

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

    Raises ``BundleError`` for anything that is not a valid bundle (see the module docstring);
    no other exception escapes for any file content (a loader failure, a RecursionError or a
    MemoryError included, is reported as a BundleError).
    """
    with _Source(source) as src:
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
    ``nets.MAX_OPERATIONS`` and ``nets.MAX_ACTIVATION_BYTES``), one blank observation with every
    move allowed goes through the network; a bundle whose forward pass takes longer than
    ``max_forward_s`` seconds (twice, so that a cold first call is forgiven) is refused.

    Raises:
        BundleError: for any refusal; no other exception escapes.
    """
    bundle = load_bundle(source, device=device)
    where = _where(source)
    try:
        seconds = dry_run_seconds(bundle)
        if seconds > max_forward_s:
            seconds = min(seconds, dry_run_seconds(bundle))
    except Exception as exc:
        raise BundleError(f"{where}: fails on a blank observation ({type(exc).__name__})") from exc
    if seconds > max_forward_s:
        raise BundleError(f"{where}: one observation takes {seconds:.2f} s to evaluate, over the "
                          f"{max_forward_s:g} s limit (too slow to act with)")
    return bundle


def dry_run_seconds(bundle: PolicyBundle) -> float:
    """Wall time of one greedy ``act`` on a blank observation with every move allowed."""
    blank = torch.zeros((1, *bundle.obs_shape), device=bundle.device)
    allowed = torch.ones((1, bundle.num_actions), dtype=torch.bool, device=bundle.device)
    start = time.perf_counter()
    with torch.no_grad():
        bundle.act(blank, allowed, greedy=True)
    if bundle.device.type == "cuda":
        torch.cuda.synchronize(bundle.device)
    return time.perf_counter() - start


def bundle_digest(source: str | os.PathLike[str] | bytes | bytearray | memoryview) -> str:
    """Hex sha256 of the bundle's bytes (no validation): a content address independent of IPFS."""
    with _Source(source) as src:
        digest = hashlib.sha256()
        for offset in range(0, src.size, 1 << 20):
            digest.update(src.read(offset, min(1 << 20, src.size - offset)))
        return digest.hexdigest()


def printable(text: str, limit: int = 200) -> str:
    """``text`` (a path, a topic message) with anything but printable ASCII shown as ``?``, cut to
    ``limit`` characters: safe to put in a message, a log line or on a terminal."""
    clean = "".join(ch if " " <= ch <= "~" else "?" for ch in text[:limit + 1])
    return clean if len(clean) <= limit else clean[:limit] + "..."


def _where(source: Any) -> str:
    if isinstance(source, bytes | bytearray | memoryview):
        return "bundle bytes"
    return printable(os.fspath(source)) if isinstance(source, str | os.PathLike) else "bundle"


class _Source:
    """Bounded reads from a path or from bytes: the header is checked before the rest is read."""

    def __init__(self, source: Any) -> None:
        self.fd: int | None = None
        if isinstance(source, bytes | bytearray | memoryview):
            self.data: bytes | None = bytes(source)
            self.size = len(self.data)
            self.where = "bundle bytes"
            return
        if not isinstance(source, str | os.PathLike):
            raise TypeError(f"expected a path or bytes, got {type(source).__name__}")
        path = Path(source)
        self.where = printable(str(path))
        self.data = None
        try:
            if not path.is_file():  # before opening: opening a FIFO or a device could block
                if path.is_dir():
                    raise BundleError(f"{self.where}: is a directory, not a bundle file")
                if not path.exists():
                    raise BundleError(f"{self.where}: no such file")
                raise BundleError(f"{self.where}: not a regular file")
            self.fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
            st = os.fstat(self.fd)
        except FileNotFoundError:
            self.close()
            raise BundleError(f"{self.where}: no such file") from None
        except OSError as exc:
            self.close()
            raise BundleError(f"{self.where}: cannot read: {exc.strerror or type(exc).__name__}") from None
        except BundleError:
            self.close()
            raise
        if not stat.S_ISREG(st.st_mode):
            self.close()
            raise BundleError(f"{self.where}: not a regular file")
        self.size = st.st_size
        if self.size > MAX_BUNDLE_BYTES:
            self.close()
            raise BundleError(f"{self.where}: {self.size} bytes is larger than the {MAX_BUNDLE_BYTES} "
                              "byte limit")

    def read(self, offset: int, count: int) -> bytes:
        """Exactly ``count`` bytes from ``offset`` (the caller checked that they exist)."""
        if self.data is not None:
            return self.data[offset:offset + count]
        chunks, done = [], 0
        try:
            while done < count:
                chunk = os.pread(self.fd, min(count - done, 16 << 20), offset + done)
                if not chunk:
                    break
                chunks.append(chunk)
                done += len(chunk)
        except OSError as exc:
            raise BundleError(f"{self.where}: cannot read: {exc.strerror or type(exc).__name__}") from None
        out = b"".join(chunks)
        if len(out) != count:
            raise BundleError(f"{self.where}: the file changed while it was read")
        return out

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> _Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _JSONLimit(ValueError):
    """A JSON text over one of this module's limits (the message names the limit, not the text)."""


# A JSON string literal (possessive: linear time on any input). Removing them leaves the brackets
# that structure the text, so nesting depth is measured without recursing.
_JSON_STRING = re.compile(r'"(?:[^"\\]++|\\.)*+"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]++")


def json_depth(text: str) -> int:
    """How deep the objects and lists of a JSON text nest, by a linear scan (no parsing, no recursion).

    Brackets inside complete string literals do not count; those of an unterminated string do
    (such a text is not JSON anyway), so the result is never below the true depth.
    """
    brackets = _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)).encode("ascii")
    if not brackets:
        return 0
    codes = np.frombuffer(brackets, dtype=np.uint8)
    steps = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1)
    return int(np.cumsum(steps).max())


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    # Two entries with one name would let a reader and a checker see different tensors.
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _JSONLimit("a key appears twice in one object")  # which key is not said: file content
        out[key] = value
    return out


def _reject_constant(name: str) -> Any:
    raise _JSONLimit(f"non-standard JSON constant {name}")


def _parse_number(kind: type) -> Any:
    def parse(text: str) -> Any:
        if len(text) > MAX_NUMBER_CHARS:
            raise _JSONLimit(f"a number of more than {MAX_NUMBER_CHARS} characters")
        value = kind(text)
        if not math.isfinite(value):
            raise _JSONLimit("a number too large for a float")
        return value
    return parse


def _check_strings(value: Any, what: str, max_string: int = MAX_STRING_CHARS) -> None:
    """Every key and string in ``value`` (depth already bounded) is valid Unicode and not over-long."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
        elif isinstance(item, str):
            if len(item) > max_string:
                raise BundleError(f"{what} holds a string of more than {max_string} characters")
            try:
                item.encode("utf-8")
            except UnicodeEncodeError:
                raise BundleError(f"{what} holds invalid Unicode (a lone surrogate, e.g. a \\ud800 "
                                  "escape)") from None


def parse_json(text: str, what: str, max_chars: int, max_string: int = MAX_STRING_CHARS) -> Any:
    """``text`` parsed as strict JSON within this module's limits; ``BundleError`` names ``what``.

    Refused, and never echoed: more than ``max_chars`` characters, nesting deeper than
    ``MAX_JSON_DEPTH`` (checked before parsing, so the parser never recurses deep), NaN/Infinity,
    numbers over ``MAX_NUMBER_CHARS`` characters or beyond float range, duplicate keys, strings or
    keys over ``max_string`` characters, and invalid Unicode (lone surrogates).
    """
    if len(text) > max_chars:
        raise BundleError(f"{what} is over the {max_chars} character limit")
    if json_depth(text) > MAX_JSON_DEPTH:
        raise BundleError(f"{what} nests deeper than {MAX_JSON_DEPTH} levels")
    try:
        value = json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_reject_constant,
                           parse_int=_parse_number(int), parse_float=_parse_number(float))
    except json.JSONDecodeError as exc:
        raise BundleError(f"{what} is not valid JSON ({exc.msg} at character {exc.pos})") from None
    except _JSONLimit as exc:
        raise BundleError(f"{what} is not valid JSON: {exc}") from None
    except (ValueError, RecursionError, MemoryError) as exc:
        raise BundleError(f"{what} is not valid JSON ({type(exc).__name__})") from None
    _check_strings(value, what, max_string)
    return value


def _parse_header(src: _Source) -> tuple[dict[str, Any], dict[str, Any], int]:
    """Check the safetensors container; return (manifest JSON, tensor table, data start).

    Reads the 8-byte length prefix, then the header, nothing more. Messages never echo the file:
    not the prefix's value, not a byte, not a snippet of the header.
    """
    where = src.where
    if src.size < 8:
        raise BundleError(f"{where}: {src.size} bytes is too short to be a safetensors file")
    (header_len,) = struct.unpack("<Q", src.read(0, 8))
    if header_len > MAX_HEADER_BYTES:
        raise BundleError(f"{where}: the header length in the first 8 bytes is over the {MAX_HEADER_BYTES} "
                          "byte limit (not a bundle, or corrupted)")
    if 8 + header_len > src.size:
        raise BundleError(f"{where}: truncated: header needs more bytes than the file's {src.size}")
    raw = src.read(8, header_len)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise BundleError(f"{where}: header is not valid JSON (not UTF-8 text); "
                          "not a safetensors file") from None
    try:
        # The header's strings are tensor names, dtypes and the manifest (checked on its own below).
        header = parse_json(text, "header", MAX_HEADER_BYTES, max_string=MAX_HEADER_BYTES)
    except BundleError as exc:
        raise BundleError(f"{where}: {exc}; not a safetensors file") from None
    if not isinstance(header, dict):
        raise BundleError(f"{where}: header must be a JSON object")
    meta = header.pop("__metadata__", None)
    if not isinstance(meta, dict) or MANIFEST_KEY not in meta:
        raise BundleError(f"{where}: no '{MANIFEST_KEY}' in the safetensors metadata: "
                          "a safetensors file, but not a MEDC policy bundle")
    if not isinstance(meta[MANIFEST_KEY], str):
        raise BundleError(f"{where}: metadata '{MANIFEST_KEY}' must be a JSON string")
    try:
        manifest = parse_json(meta[MANIFEST_KEY], "manifest", MAX_MANIFEST_CHARS)
    except BundleError as exc:
        raise BundleError(f"{where}: {exc}") from None
    return manifest, header, 8 + header_len


def _check_table(table: dict[str, Any], data_len: int, where: str) -> None:
    """Each entry is F32 with a shape whose size matches its byte range; ranges tile the data exactly."""
    spans = []
    for name, entry in table.items():
        label = safe_repr(name)
        if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
            raise BundleError(f"{where}: tensor {label}: entry must have dtype, shape, data_offsets")
        if entry["dtype"] not in _DTYPE_SIZES:
            raise BundleError(f"{where}: tensor {label} has dtype {safe_repr(entry['dtype'], 8)}; "
                              "bundles hold F32 only")
        shape, offsets = entry["shape"], entry["data_offsets"]
        if (not isinstance(shape, list) or len(shape) > 8
                or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)):
            raise BundleError(f"{where}: tensor {label} has an invalid shape (at most 8 non-negative "
                              "integers)")
        if (not isinstance(offsets, list) or len(offsets) != 2
                or not all(isinstance(o, int) and not isinstance(o, bool) for o in offsets)
                or not 0 <= offsets[0] <= offsets[1]):
            raise BundleError(f"{where}: tensor {label} has invalid data_offsets")
        if offsets[1] - offsets[0] != math.prod(shape) * _DTYPE_SIZES[entry["dtype"]]:
            raise BundleError(f"{where}: tensor {label}: its shape does not fit its byte range")
        spans.append((offsets[0], offsets[1], name))
    spans.sort()
    cursor = 0
    for start, end, name in spans:
        if start != cursor:
            raise BundleError(f"{where}: tensor {safe_repr(name)} data does not follow the previous "
                              "tensor (overlap or gap): corrupted file")
        cursor = end
    if cursor > data_len:
        raise BundleError(f"{where}: truncated: tensors need more data bytes than the file holds")
    if cursor < data_len:
        raise BundleError(f"{where}: unexpected bytes after the last tensor")


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
    return manifest, tensors, data


# ---------------------------------------------------------------------------------------------
# Training checkpoints (no pickle)

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
