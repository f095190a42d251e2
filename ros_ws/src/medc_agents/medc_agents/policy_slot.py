"""The policy an agent node runs, and swapping it safely at runtime (no ROS in here).

A bundle file is data from a stranger: it is loaded only by ``medc_training.bundle.load_untrusted``
(safetensors + a validated JSON manifest, never pickle; compute and memory caps; a timed dry run)
and must fit this agent's observation and action space before it replaces the running policy.
Anything else is refused with a :class:`PolicyRejected` that says why (never echoing the file),
and the old policy keeps running. A classical controller's name (``gradient``, ``greedy``,
``infotaxis``: :mod:`medc_agents.controller`) is a policy too: it needs no file.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import torch
from medc_training.envs.names import DEFAULT_APPLICATION
from medc_training.envs.tl_sensing import DEFAULT_SENSING
from medc_training.untrusted import MAX_BUNDLE_BYTES, printable

from medc_agents.controller import ControllerPolicy, controller_name, controller_scenario

_CID = re.compile(r"^(ipfs://|cid:)?(Qm[1-9A-HJ-NP-Za-km-z]{44}|b[a-z2-7]{20,})$")


class PolicyRejected(ValueError):
    """A bundle cannot be used by this agent; the message says why and what to send instead."""


def looks_like_cid(source: str) -> bool:
    """True for an IPFS content id (``Qm...``, ``b...``, optionally ``ipfs://`` or ``cid:``)."""
    return len(source) <= 200 and bool(_CID.match(source.strip()))


def shown(source: object) -> str:
    """A policy source as messages and logs show it: printable ASCII only, quoted, at most 200
    characters (a topic message or a parameter is anyone's text)."""
    text = source if isinstance(source, str) else repr(source)
    return "'" + printable(text, 200, drop="'\\") + "'"


def strip_cid(source: str) -> str:
    """The bare CID of ``ipfs://<cid>`` / ``cid:<cid>`` / ``<cid>``."""
    m = _CID.match(source.strip()) if len(source) <= 200 else None
    if not m:
        raise PolicyRejected(f"{shown(source)} is not an IPFS content id")
    return m.group(2)


@dataclass
class LoadedPolicy:
    """A validated bundle and where it came from, with its deciders (one per runtime asked for)."""

    bundle: object
    source: str
    _deciders: dict = field(default_factory=dict, repr=False, compare=False)

    def decider(self, runtime: str = "auto"):
        """The bundle's :class:`medc_training.bundle.runtime.Decider` in ``runtime`` ('auto',
        'onnxruntime', 'torch'), made once and kept.

        Raises:
            PolicyRejected: ``runtime`` is unknown, or 'onnxruntime' cannot run this bundle here.
        """
        if runtime not in self._deciders:
            from medc_training.bundle.runtime import RuntimeUnavailable, decider

            try:
                self._deciders[runtime] = decider(self.bundle, runtime)
            except (ValueError, RuntimeUnavailable) as exc:
                raise PolicyRejected(f"policy bundle {shown(self.source)}: {exc}") from exc
        return self._deciders[runtime]

    @property
    def description(self) -> str:
        from medc_training.nets import safe_repr

        arch = self.bundle.manifest.get("architecture", {})
        name = safe_repr(arch.get("name", "?"))[1:-1] if isinstance(arch, dict) else "?"
        return f"{shown(self.source)[1:-1]} ({name})"


def load_policy(
    source: str,
    obs_shape: tuple[int, int, int],
    num_actions: int,
    application: str | None = DEFAULT_APPLICATION,
    max_forward_s: float | None = None,
    observation: str | None = None,
    sensing: str | None = None,
    allow_other_world: bool = False,
    world: str = "grid",
) -> LoadedPolicy:
    """Load and validate the bundle file at ``source`` for this observation/action space.

    The bundle goes through ``medc_training.bundle.load_untrusted`` (every static check, the
    compute and memory caps, then a dry run that must take at most ``max_forward_s`` seconds,
    default ``MAX_FORWARD_SECONDS``), the same function the registry bridge vets fetched bundles
    with, and must then fit this agent's observation shape, action count and application.
    ``observation`` names the observation variant this agent builds (target localization); a
    bundle that takes another variant is refused. ``sensing`` names the team's sensing preset
    (``medc_training.envs.tl_sensing.SENSING_PRESETS``): a target-localization bundle trained under
    another (its manifest's ``environment.sensing``; none = 'paper-simple') is refused, the message
    naming both (or the team's model itself, the benchmark's with its background prior: a bundle
    whose manifest records another prior is refused); None checks nothing. A bundle trained in
    another world than ``world`` (the graph's: ``grid`` or ``radbench``) or with domain randomisation
    (``medc_training.bundle.check_world``) is refused unless ``allow_other_world``.

    Raises:
        PolicyRejected: for every refusal and for any failure while loading (a RecursionError or
        a MemoryError included): no other exception escapes, whatever the file holds.
    """
    try:
        return _load_policy(source, obs_shape, num_actions, application, max_forward_s, observation, sensing,
                            allow_other_world, world)
    except PolicyRejected:
        raise
    except Exception as exc:  # a file or a message must never take the node down
        raise PolicyRejected(
            f"policy bundle {shown(source)} could not be loaded ({type(exc).__name__})"
        ) from exc


def _bundle_path(source) -> Path:
    """The path of an existing, not oversized bundle file ``source``; PolicyRejected says why not."""
    if not isinstance(source, str) or not source.strip():
        raise PolicyRejected("empty policy source: send the path of a .safetensors policy bundle")
    if "\x00" in source:
        raise PolicyRejected("policy path contains a NUL byte")
    if looks_like_cid(source):
        raise PolicyRejected(
            f"{shown(source)} is a content id: fetch it through the registry bridge (service "
            "fetch_bundle), which verifies it and sends this agent the local path"
        )
    path = Path(source).expanduser()
    try:
        if not path.is_file():
            raise PolicyRejected(f"policy bundle {shown(source)} is not an existing file")
        size = path.stat().st_size
    except PolicyRejected:
        raise
    except (OSError, ValueError) as exc:
        why = getattr(exc, "strerror", None) or type(exc).__name__
        raise PolicyRejected(f"cannot read policy bundle {shown(source)}: {why}") from exc
    if size > MAX_BUNDLE_BYTES:
        raise PolicyRejected(f"policy bundle {shown(source)} is {size} bytes, more than {MAX_BUNDLE_BYTES}")
    return path


def read_policy_manifest(source) -> dict:
    """The validated manifest of the bundle file ``source`` (its weights are not read).

    Raises:
        PolicyRejected: the reasons :func:`load_policy` gives for the file, or an invalid manifest;
        no other exception escapes, whatever the file holds.
    """
    from medc_training.bundle import BundleError, read_manifest

    path = _bundle_path(source)
    try:
        return read_manifest(path)
    except BundleError as exc:
        raise PolicyRejected(f"policy bundle {shown(source)} is invalid: {exc}") from exc
    except Exception as exc:  # a file must never take the node down
        why = type(exc).__name__
        raise PolicyRejected(f"policy bundle {shown(source)} could not be loaded ({why})") from exc


def _load_policy(source, obs_shape, num_actions, application, max_forward_s, observation,
                 sensing=None, allow_other_world=False, world="grid") -> LoadedPolicy:
    from medc_training.bundle import (
        MAX_FORWARD_SECONDS,
        BundleError,
        check_sensing,
        check_world,
        load_untrusted,
    )
    from medc_training.envs import core_options
    from medc_training.experts import BundleExpert, ExpertError

    path = _bundle_path(source)
    limit = MAX_FORWARD_SECONDS if max_forward_s is None else max_forward_s
    try:
        bundle = load_untrusted(path, device="cpu", max_forward_s=limit)
    except BundleError as exc:
        raise PolicyRejected(f"policy bundle {shown(source)} is invalid: {exc}") from exc
    try:
        BundleExpert(bundle).check_compatible(obs_shape, num_actions, observation=observation,
                                              application=application)
    except ExpertError as exc:
        raise PolicyRejected(str(exc)) from exc
    try:
        if sensing is not None and "sensing" in core_options(bundle.manifest.get("application")):
            check_sensing(bundle.manifest, sensing, f"policy bundle {shown(source)}")
        check_world(bundle.manifest, world, allow_other_world, f"policy bundle {shown(source)}")
    except BundleError as exc:
        raise PolicyRejected(str(exc)) from exc
    return LoadedPolicy(bundle=bundle, source=str(path))


#: Validated bundles by (path, size, mtime): agents of one process loading the same file share one
#: PolicyBundle (loaded and checked once), which also lets a TeamFeed batch their forward passes.
#: The least recently used are forgotten beyond ``MAX_CACHED_POLICIES`` bundles or
#: ``MAX_CACHED_POLICY_BYTES`` bytes of weights (the latest is always kept); a forgotten bundle that
#: no agent runs any more is freed, and one asked for again is loaded and checked again.
_LOADED: OrderedDict[tuple[str, int, int, tuple, int, str | None, str | None, object, bool, str],
                     LoadedPolicy] = OrderedDict()
MAX_CACHED_POLICIES = 4
MAX_CACHED_POLICY_BYTES = 64 << 20


def _weight_bytes(loaded: LoadedPolicy) -> int:
    return sum(p.numel() * p.element_size() for p in loaded.bundle.net.parameters())


def _evict() -> None:
    """Forget the least recently used bundles beyond the count and byte bounds (never the latest)."""
    total = sum(_weight_bytes(v) for v in _LOADED.values())
    while len(_LOADED) > 1 and (len(_LOADED) > MAX_CACHED_POLICIES or total > MAX_CACHED_POLICY_BYTES):
        _, old = _LOADED.popitem(last=False)
        total -= _weight_bytes(old)


def load_policy_cached(
    source: str,
    obs_shape: tuple[int, int, int],
    num_actions: int,
    application: str | None = DEFAULT_APPLICATION,
    max_forward_s: float | None = None,
    observation: str | None = None,
    sensing: str | None = None,
    allow_other_world: bool = False,
    world: str = "grid",
) -> LoadedPolicy:
    """:func:`load_policy`, reusing a bundle already validated in this process for the same file."""
    try:
        st = Path(source).expanduser().stat()
        key = (
            str(Path(source).expanduser().resolve()),
            st.st_size,
            st.st_mtime_ns,
            tuple(obs_shape),
            num_actions,
            application,
            observation,
            sensing,
            bool(allow_other_world),
            world,
        )
    except Exception:  # not stat-able (or not a path): load_policy gives the reason
        return load_policy(source, obs_shape, num_actions, application, max_forward_s, observation, sensing,
                           allow_other_world, world)
    if key not in _LOADED:
        _LOADED[key] = load_policy(source, obs_shape, num_actions, application, max_forward_s, observation,
                                   sensing, allow_other_world, world)
    _LOADED.move_to_end(key)
    loaded = _LOADED[key]
    _evict()
    return loaded


class PolicySlot:
    """The running policy of one agent, replaced only by a bundle that validates."""

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        num_actions: int,
        application: str | None = DEFAULT_APPLICATION,
        max_forward_s: float | None = None,
        observation: str | None = None,
        grid: int | None = None,
        sensing: str | None = DEFAULT_SENSING,
        allow_other_world: bool = False,
        runtime: str = "auto",
        world: str = "grid",
    ) -> None:
        """``observation``: the target-localization observation variant a bundle must take; None
        with a ``grid`` means "the one the bundle's manifest names" (its shape on that grid is then
        the observation shape, and :attr:`observation` follows the running bundle). ``sensing``:
        the team's sensing preset or model; a bundle trained under another is refused (None: no
        check). ``world``: the graph's world (``grid``, ``radbench``); ``allow_other_world``: take a
        bundle trained in another world or with domain randomisation (refused otherwise).
        ``runtime``: what runs a bundle's network (:mod:`medc_training.bundle.runtime`: 'auto'
        takes onnxruntime where it agrees with PyTorch, else PyTorch; 'onnxruntime' refuses a
        bundle it cannot run; 'torch')."""
        from medc_training.bundle.runtime import RUNTIMES

        if runtime not in RUNTIMES:
            raise ValueError(f"runtime must be one of {', '.join(RUNTIMES)}, got {str(runtime)[:40]!r}")
        self.runtime = runtime
        self.obs_shape = tuple(obs_shape)
        self.num_actions = num_actions
        self.application = application
        self.max_forward_s = max_forward_s
        self.observation = observation
        self.follow_bundle = observation is None and grid is not None
        self.grid = grid
        self.sensing = sensing
        self.allow_other_world = bool(allow_other_world)
        self.world = world
        self.current: LoadedPolicy | ControllerPolicy | None = None

    @property
    def controller(self) -> str | None:
        """The name of the running classical controller, or None (a bundle, or nothing yet)."""
        return self.current.controller if isinstance(self.current, ControllerPolicy) else None

    def swap(self, source: str) -> LoadedPolicy | ControllerPolicy:
        """Validate ``source`` (a bundle path, or a controller's name) and make it the running policy.

        Raises:
            PolicyRejected: the bundle was refused; the previous policy is still running.
        """
        name = controller_name(source)
        if name is not None:
            try:
                controller_scenario(name, 1, 1, self.application)
            except ValueError as exc:
                raise PolicyRejected(str(exc)) from None
            self.current = ControllerPolicy(name)
            return self.current
        obs_shape, observation = self.obs_shape, self.observation
        if self.follow_bundle:
            obs_shape, observation = self._bundle_observation(source)
        loaded = load_policy_cached(source, obs_shape, self.num_actions, self.application,
                                    self.max_forward_s, observation, self.sensing, self.allow_other_world,
                                    self.world)
        loaded.decider(self.runtime)  # made (and checked) before the policy runs
        self.current = loaded
        self.obs_shape, self.observation = obs_shape, observation
        return loaded

    def _bundle_observation(self, source: str) -> tuple[tuple[int, int, int], str]:
        """(shape on this grid, name) of the observation the bundle at ``source`` names."""
        from medc_training.bundle import manifest_observation
        from medc_training.envs.observation import parse_observation
        from medc_training.envs.tl_observation import observation_shape

        manifest = read_policy_manifest(source)
        try:
            spec = parse_observation(manifest_observation(manifest))
        except ValueError as exc:
            raise PolicyRejected(f"policy bundle {shown(source)} is invalid: {exc}") from exc
        return observation_shape(spec, self.grid), spec.name

    @torch.no_grad()
    def act(self, obs: torch.Tensor, mask: torch.Tensor) -> int:
        """Greedy action for one observation ``[C,H,W]`` and its move mask ``[A]``.

        Raises:
            RuntimeError: no policy loaded yet.
        """
        if self.current is None:
            raise RuntimeError("no policy loaded: set the agent's 'policy' parameter to a bundle path")
        if self.controller is not None:
            raise RuntimeError(f"controller {self.controller} decides from the team's state, not an "
                               "observation: medc_agents.controller.controller_move")
        action = self.decider.act(obs.unsqueeze(0), mask.unsqueeze(0))
        return int(action[0])

    def runs_in(self) -> str:
        """What the logs add after a bundle's description: ``, network in <runtime>`` and, where
        'auto' took PyTorch, why (empty for a controller or nothing)."""
        decider = self.decider
        if decider is None:
            return ""
        return f", network in {decider.runtime}" + (f" ({decider.note})" if decider.note else "")

    @property
    def decider(self):
        """The running bundle's decider in this slot's runtime (None for a controller or nothing)."""
        if not isinstance(self.current, LoadedPolicy):
            return None
        return self.current.decider(self.runtime)
