"""The policy an agent node runs, and swapping it safely at runtime (no ROS in here).

A bundle file is data from a stranger: it is loaded only by ``medc_training.bundle.load_bundle``
(safetensors + a validated JSON manifest, never pickle) and must fit this agent's observation
and action space before it replaces the running policy. Anything else is refused with a
:class:`PolicyRejected` that says why, and the old policy keeps running.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import torch

#: A bundle is a few MB at most; refuse anything far larger before reading it.
MAX_BUNDLE_BYTES = 256 * 1024 * 1024

_CID = re.compile(r"^(ipfs://|cid:)?(Qm[1-9A-HJ-NP-Za-km-z]{44}|b[a-z2-7]{20,})$")


class PolicyRejected(ValueError):
    """A bundle cannot be used by this agent; the message says why and what to send instead."""


def looks_like_cid(source: str) -> bool:
    """True for an IPFS content id (``Qm...``, ``b...``, optionally ``ipfs://`` or ``cid:``)."""
    return bool(_CID.match(source.strip()))


def strip_cid(source: str) -> str:
    """The bare CID of ``ipfs://<cid>`` / ``cid:<cid>`` / ``<cid>``."""
    m = _CID.match(source.strip())
    if not m:
        raise PolicyRejected(f"{source!r} is not an IPFS content id")
    return m.group(2)


@dataclass
class LoadedPolicy:
    """A validated bundle and where it came from."""

    bundle: object
    source: str

    @property
    def description(self) -> str:
        arch = self.bundle.manifest.get("architecture", {})
        name = arch.get("name", "?") if isinstance(arch, dict) else "?"
        return f"{self.source} ({name})"


def load_policy(
    source: str,
    obs_shape: tuple[int, int, int],
    num_actions: int,
    application: str | None = "target_localization",
    observation: str | None = None,
) -> LoadedPolicy:
    """Load and validate the bundle file at ``source`` for this observation/action space.

    ``observation`` names the observation variant this agent builds (target localization); a
    bundle that takes another variant is refused.

    Raises:
        PolicyRejected: not a readable regular file, too large, not a valid bundle, or made for
        another observation shape / action count / application.
    """
    from medc_training.bundle import BundleError, load_bundle
    from medc_training.experts import BundleExpert, ExpertError

    if not isinstance(source, str) or not source.strip():
        raise PolicyRejected("empty policy source: send the path of a .safetensors policy bundle")
    if "\x00" in source:
        raise PolicyRejected("policy path contains a NUL byte")
    if looks_like_cid(source):
        raise PolicyRejected(
            f"{source!r} is a content id: fetch it through the registry bridge (service fetch_bundle), "
            "which verifies it and sends this agent the local path"
        )
    path = Path(source).expanduser()
    try:
        if not path.is_file():
            raise PolicyRejected(f"policy bundle {source!r} is not an existing file")
        size = path.stat().st_size
    except OSError as exc:
        raise PolicyRejected(f"cannot read policy bundle {source!r}: {exc}") from exc
    if size > MAX_BUNDLE_BYTES:
        raise PolicyRejected(f"policy bundle {source!r} is {size} bytes, more than {MAX_BUNDLE_BYTES}")
    try:
        bundle = load_bundle(path, device="cpu")
    except BundleError as exc:
        raise PolicyRejected(f"policy bundle {source!r} is invalid: {exc}") from exc
    except (OSError, ValueError) as exc:  # a loader bug or an unreadable file must not kill the node
        raise PolicyRejected(f"policy bundle {source!r} could not be loaded: {exc}") from exc
    try:
        BundleExpert(bundle).check_compatible(obs_shape, num_actions, observation=observation,
                                              application=application)
    except ExpertError as exc:
        raise PolicyRejected(str(exc)) from exc
    # A dry run on a blank observation catches a spec whose shapes fit the manifest but not the net.
    try:
        with torch.no_grad():
            blank = torch.zeros((1, *obs_shape))
            bundle.act(blank, torch.ones((1, num_actions), dtype=torch.bool), greedy=True)
    except (RuntimeError, ValueError) as exc:
        raise PolicyRejected(f"policy bundle {source!r} fails on a {obs_shape} observation: {exc}") from exc
    return LoadedPolicy(bundle=bundle, source=str(path))


#: Validated bundles by (path, size, mtime): agents of one process loading the same file share one
#: PolicyBundle (loaded and checked once), which also lets a TeamFeed batch their forward passes.
_LOADED: dict[tuple[str, int, int, tuple, int, str | None, str | None], LoadedPolicy] = {}


def load_policy_cached(
    source: str,
    obs_shape: tuple[int, int, int],
    num_actions: int,
    application: str | None = "target_localization",
    observation: str | None = None,
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
        )
    except (OSError, ValueError):
        return load_policy(source, obs_shape, num_actions, application, observation)  # the precise reason
    if key not in _LOADED:
        _LOADED[key] = load_policy(source, obs_shape, num_actions, application, observation)
    return _LOADED[key]


class PolicySlot:
    """The running policy of one agent, replaced only by a bundle that validates."""

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        num_actions: int,
        application: str | None = "target_localization",
        observation: str | None = None,
        grid: int | None = None,
    ) -> None:
        """``observation``: the target-localization observation variant a bundle must take; None
        with a ``grid`` means "the one the bundle's manifest names" (its shape on that grid is then
        the observation shape, and :attr:`observation` follows the running bundle)."""
        self.obs_shape = tuple(obs_shape)
        self.num_actions = num_actions
        self.application = application
        self.observation = observation
        self.follow_bundle = observation is None and grid is not None
        self.grid = grid
        self.current: LoadedPolicy | None = None

    def swap(self, source: str) -> LoadedPolicy:
        """Validate ``source`` and make it the running policy.

        Raises:
            PolicyRejected: the bundle was refused; the previous policy is still running.
        """
        obs_shape, observation = self.obs_shape, self.observation
        if self.follow_bundle:
            obs_shape, observation = self._bundle_observation(source)
        loaded = load_policy_cached(source, obs_shape, self.num_actions, self.application, observation)
        self.current = loaded
        self.obs_shape, self.observation = obs_shape, observation
        return loaded

    def _bundle_observation(self, source: str) -> tuple[tuple[int, int, int], str]:
        """(shape on this grid, name) of the observation the bundle at ``source`` names."""
        from medc_training.bundle import BundleError, read_manifest
        from medc_training.envs.target_localization import check_observation

        if not isinstance(source, str) or looks_like_cid(source) or not Path(source).expanduser().is_file():
            load_policy(source, self.obs_shape, self.num_actions, self.application)  # the precise reason
        try:
            manifest = read_manifest(Path(source).expanduser())
            spec = check_observation(manifest["observation"].get("name", "maps"), self.grid)
        except (BundleError, ValueError, KeyError, TypeError, OSError) as exc:
            raise PolicyRejected(f"policy bundle {source!r} is invalid: {exc}") from exc
        return spec.shape(self.grid), spec.name

    @torch.no_grad()
    def act(self, obs: torch.Tensor, mask: torch.Tensor) -> int:
        """Greedy action for one observation ``[C,H,W]`` and its move mask ``[A]``.

        Raises:
            RuntimeError: no policy loaded yet.
        """
        if self.current is None:
            raise RuntimeError("no policy loaded: set the agent's 'policy' parameter to a bundle path")
        action = self.current.bundle.act(obs.unsqueeze(0), mask.unsqueeze(0), greedy=True)
        return int(action[0])
