"""Where a registry lives: the chain, the contracts, the signing keys and the content store.

Two ways to say it, both ending in one :class:`RegistrySettings`:

* a **home** folder (``--home``, ``$MEDC_HOME`` or ``./.medc``), as ``medc-registry start`` /
  ``deploy`` leave it: ``registry.json`` records the chain (JSON-RPC URL, PoA or not, contract
  addresses), the content store and, for a node started there, the anvil process; signing keys
  come from ``$MEDC_PRIVATE_KEY``, the recorded key file and the local node's funded accounts;
  paid requests are recorded in ``pending-requests.json`` before they are sent
  (:func:`home_settings`);
* a **spec** of strings, as the bridge node's parameters and the demo give it: ``chain``
  ("embedded" or a JSON-RPC URL), ``content`` (a local folder or an IPFS API URL), the contract
  addresses and a key file (:func:`spec_settings`).

``Registry.from_settings`` (medc_registry.registry) opens a registry from either; the CLI, the
bridge node and the demo all go through it, so the store and chain are chosen in one place.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .chain import ChainClient, ChainError
from .content import ContentStore, KuboContentStore, LocalContentStore

STATE_FILE = "registry.json"
#: Paid requests sent but not confirmed yet (written before each payment is sent).
PENDING_FILE = "pending-requests.json"
#: The funded development keys of the anvil node ``medc-registry start`` runs.
ANVIL_ACCOUNTS_FILE = "anvil-accounts.json"
#: The ``chain`` of a spec that means an in-process eth-tester chain with fresh contracts.
EMBEDDED = "embedded"
#: Total seconds one chain call may take, retries included, for a registry opened from a home
#: (the CLI's ``--deadline`` default).
HOME_DEADLINE = 30.0
#: URL prefixes of endpoints on this machine.
LOOPBACK = ("http://127.0.0.1", "http://localhost", "http://[::1]")


class RegistryHomeError(RuntimeError):
    """A home or spec that does not give a usable registry; the message says what to do."""


@dataclass(frozen=True)
class RegistrySettings:
    """Everything needed to open a registry (see the module docstring)."""

    #: "embedded" or a JSON-RPC URL.
    chain: str
    #: ``{"kind": "local", "root": DIR}`` or ``{"kind": "kubo", "url": URL}``.
    content: Mapping[str, str]
    users_manager: str = ""
    models_manager: str = ""
    #: Signing keys, account 0 first (none for the embedded chain: it has its own).
    keys: tuple[str, ...] = ()
    #: A Besu/Quorum proof-of-authority chain (long extraData).
    poa: bool = False
    #: The home the settings were read from (paid requests are recorded there); None for a spec.
    home: Path | None = None
    #: The chain is the anvil node `medc-registry start` runs in ``home``.
    local_node: bool = False

    @property
    def embedded(self) -> bool:
        return self.chain == EMBEDDED

    @property
    def pending_file(self) -> Path | None:
        """Where paid requests are recorded before they are sent (None: in memory only)."""
        return None if self.home is None else self.home / PENDING_FILE

    def open_store(self) -> ContentStore:
        """The content store the settings name."""
        if self.content["kind"] == "kubo":
            return KuboContentStore(self.content["url"])
        return LocalContentStore(self.content["root"])

    def open_chain(self, deadline: float | None = None) -> ChainClient:
        """A client for the chain: a new embedded one, or the JSON-RPC node signing with ``keys``.

        Raises:
            RegistryHomeError: no signing key, or the node does not answer within ``deadline`` s.
        """
        if self.embedded:
            return ChainClient.embedded()
        if not self.keys:
            raise RegistryHomeError("no signing keys: set MEDC_PRIVATE_KEY or deploy with --key-file")
        kwargs: dict[str, Any] = {}
        if deadline is not None:
            kwargs = {"timeout": min(10.0, deadline), "deadline": deadline}
        try:
            return ChainClient.connect(self.chain, list(self.keys), poa=self.poa, **kwargs)
        except ChainError as exc:
            hint = " (run `medc-registry start` to restart the local node)" if self.local_node else ""
            raise RegistryHomeError(f"chain at {self.chain} is not reachable{hint}: {exc}") from None


# ---------------------------------------------------------------- a home folder
def home_dir(home: str | os.PathLike[str] | None = None) -> Path:
    """The home folder: ``home``, else ``$MEDC_HOME``, else ``./.medc`` (absolute)."""
    return Path(home or os.environ.get("MEDC_HOME") or ".medc").resolve()


def load_state(home: Path) -> dict[str, Any]:
    """``registry.json`` of ``home``.

    Raises:
        RegistryHomeError: there is none; the message names the commands that make one.
    """
    path = home / STATE_FILE
    if not path.is_file():
        raise RegistryHomeError(
            f"no registry configured in {home}: run `medc-registry start` (local anvil node) or "
            "`medc-registry deploy --rpc URL --key-file FILE` first, or pass --home DIR"
        )
    return json.loads(path.read_text())


def save_state(home: Path, state: Mapping[str, Any]) -> None:
    """Write ``registry.json`` atomically, never through a link (:func:`medc_registry.files.write_atomic`)."""
    from .files import write_atomic

    home.mkdir(parents=True, exist_ok=True)
    write_atomic(home / STATE_FILE, (json.dumps(state, indent=2) + "\n").encode(), mode=0o644)


def read_key_file(path: str | os.PathLike[str]) -> list[str]:
    """The hex private keys of a key file, one per line (blank lines skipped).

    Raises:
        OSError: the file cannot be read.
    """
    return [ln.strip() for ln in Path(path).read_text().splitlines() if ln.strip()]


def home_keys(home: Path, state: Mapping[str, Any]) -> list[str]:
    """Signing keys of a home, account 0 first: ``$MEDC_PRIVATE_KEY``, then the recorded key
    file's, then (for a node started in ``home``) the node's funded development accounts."""
    keys: list[str] = []
    env_key = os.environ.get("MEDC_PRIVATE_KEY")
    if env_key:
        keys.append(env_key.strip())
    if state.get("key_file"):
        keys += read_key_file(state["key_file"])
    if state.get("node"):
        accounts = home / ANVIL_ACCOUNTS_FILE
        if accounts.is_file():
            keys += json.loads(accounts.read_text()).get("private_keys", [])
    return keys


def state_settings(home: Path, state: Mapping[str, Any]) -> RegistrySettings:
    """The settings a home's state (``registry.json``, possibly still being written) records."""
    return RegistrySettings(
        chain=state["rpc_url"],
        content=state.get("content", {"kind": "local", "root": str(home / "content")}),
        users_manager=state.get("users_manager", ""),
        models_manager=state.get("models_manager", ""),
        keys=tuple(home_keys(home, state)),
        poa=bool(state.get("poa", False)),
        home=home,
        local_node=bool(state.get("node")),
    )


def home_settings(home: str | os.PathLike[str] | None = None) -> RegistrySettings:
    """The registry recorded in ``home`` (see :func:`home_dir`).

    Raises:
        RegistryHomeError: no registry is configured there.
    """
    path = home_dir(home)
    return state_settings(path, load_state(path))


# ---------------------------------------------------------------- a spec of strings
def is_loopback(url: str) -> bool:
    """Whether ``url`` is an http endpoint on this machine."""
    return url.startswith(LOOPBACK)


def content_spec(text: str) -> dict[str, str]:
    """The content store a string names: an http(s) URL is an IPFS (Kubo) API, anything else a
    local folder; "" is a new temporary folder."""
    if text.startswith("http"):
        return {"kind": "kubo", "url": text}
    return {"kind": "local", "root": text or tempfile.mkdtemp(prefix="medc-store-")}


def spec_settings(
    chain: str,
    content: str = "",
    users_manager: str = "",
    models_manager: str = "",
    key_file: str = "",
    *,
    loopback_only: bool = False,
) -> RegistrySettings:
    """Settings from strings: ``chain`` "embedded" (an in-process chain with fresh contracts) or a
    JSON-RPC URL, which needs both contract addresses and ``key_file`` (one hex key per line, so
    that no key is ever a parameter other processes can read); ``content``: see
    :func:`content_spec`. ``loopback_only``: every URL must be on this machine.

    Raises:
        RegistryHomeError: a URL off loopback (with ``loopback_only``), a JSON-RPC chain without
        the contract addresses, or a key file that cannot be read or holds no key.
    """
    store = content_spec(content)
    if loopback_only and store["kind"] == "kubo" and not is_loopback(store["url"]):
        raise RegistryHomeError(f"content API {content!r} must be on loopback (127.0.0.1)")
    if chain == EMBEDDED:
        return RegistrySettings(EMBEDDED, store)
    if not chain.startswith("http") or (loopback_only and not is_loopback(chain)):
        where = "on loopback" if loopback_only else "(http or https)"
        raise RegistryHomeError(f"chain {chain!r} must be {EMBEDDED!r} or a JSON-RPC URL {where}")
    if not (users_manager and models_manager):
        raise RegistryHomeError(
            "users_manager and models_manager contract addresses are required with a JSON-RPC chain"
        )
    try:
        keys = read_key_file(key_file)
    except OSError as exc:
        raise RegistryHomeError(f"cannot read private key file {key_file!r}: {exc}") from exc
    if not keys:
        raise RegistryHomeError(f"private key file {key_file!r} holds no key (one hex key per line)")
    return RegistrySettings(chain, store, users_manager, models_manager, tuple(keys))
