"""medc-bridge: the registry bridge node. It exposes the MEDC registry to the ROS graph.

Services (medc_interfaces/srv, under ``<namespace>/registry/``; the names are relative to the node's
namespace, ``/medc`` unless ``-r __ns:=/team2`` moves it):
  request_experts  request experts meeting requirements (the Models Manager allocates them and
                   this bridge's account pays)
  fetch_bundle     fetch a bundle by CID from the content store, verify it (content hash, then
                   bundle validation) and hand it to agent nodes: its local path is published on
                   ``<namespace>/<agent_id>/policy``, which makes the agent swap to it
  submit_review    review an allocation (by id, or the latest one of a CID)

The registry logic lives in :class:`RegistryBridge` (plain Python, tested without ROS); the node
only translates services. Connection parameters: ``chain`` ("embedded" or a JSON-RPC URL on
loopback), ``users_manager``/``models_manager`` contract addresses, ``private_key_file``,
``content`` (a local store folder or an IPFS API URL on loopback), ``cache_dir``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from medc_common.ros_env import require_interfaces
from medc_training.untrusted import UntrustedJSONError, parse_json, printable

#: Longest ``requirements_json`` / ``weights_json`` a service call may carry (8 features of a
#: short name each fit in a few hundred characters).
MAX_REQUEST_JSON_CHARS = 4096


class BridgeError(ValueError):
    """A bridge request that cannot be served; the message says why."""


class RegistryBridge:
    """The registry operations the bridge serves, over one :class:`medc_registry.Registry`."""

    def __init__(self, registry: Any, cache_dir: str | os.PathLike[str]) -> None:
        self.registry = registry
        self.cache_dir = Path(cache_dir)
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        #: Latest allocation id per CID requested through this bridge (for reviews by CID).
        self.allocations: dict[str, int] = {}

    @staticmethod
    def _json_object(text: str, what: str) -> dict[str, Any] | None:
        """``text`` (from a service call) as a JSON object, read by the same bounded reader as
        bundle manifests (:func:`medc_training.untrusted.parse_json`): size, depth, numbers and
        strings are bounded before the parser recurses, whatever the process's recursion limit."""
        if not isinstance(text, str) or not text.strip():
            return None
        try:
            value = parse_json(text, what, MAX_REQUEST_JSON_CHARS)
        except UntrustedJSONError as exc:
            raise BridgeError(str(exc)) from None
        if not isinstance(value, dict):
            raise BridgeError(
                f"{what} must be a JSON object (feature name -> value), got {type(value).__name__}"
            )
        return value

    def request(
        self,
        application: str,
        requirements_json: str,
        weights_json: str = "",
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
    ) -> list[Any]:
        """Request up to ``count`` experts; returns the registry's allocations, best first.

        Raises:
            BridgeError: malformed requirements or weights, or the registry refused.
        """
        requirements = self._json_object(requirements_json, "requirements_json")
        if requirements is None:
            raise BridgeError('requirements_json is required, e.g. {"agents": 3, "walls": 2}')
        weights = self._json_object(weights_json, "weights_json")
        try:
            allocs = self.registry.request_models(
                application,
                requirements,
                weights,
                count=max(1, int(count)),
                min_model_rep=min_model_rep,
                min_owner_rep=min_owner_rep,
            )
        except (ValueError, RuntimeError) as exc:  # ChainError and ContractRevert are RuntimeErrors
            raise BridgeError(f"registry refused the request: {exc}") from exc
        for a in allocs:
            self.allocations[a.cid] = a.allocation_id
        return allocs

    def fetch(self, cid: str) -> tuple[Path, dict[str, Any]]:
        """Fetch ``cid``, verify it, and store it as ``<cache_dir>/<cid>.safetensors``.

        Returns (path, manifest). The content store checks the bytes against the CID; the bundle
        is then vetted by ``medc_training.bundle.load_untrusted``, the very function the agent
        nodes use before a swap (manifest, tensor names and shapes, compute and memory caps, a
        timed dry run), without unpickling. Only a bundle that passes is cached and handed out.

        Raises:
            BridgeError: malformed CID, not found, content mismatch, or an invalid bundle; any
            other failure while vetting (a RecursionError, a MemoryError) is a BridgeError too.
        """
        from medc_training.bundle import BundleError, load_untrusted

        from medc_registry.cid import ContentMismatchError
        from medc_registry.content import ContentStoreError

        cid = cid.strip().removeprefix("ipfs://")
        if not cid or "/" in cid or "\x00" in cid or cid.startswith("."):
            raise BridgeError(f"{cid!r} is not a content id")
        try:
            data = self.registry.fetch(cid)
        except (ContentStoreError, ContentMismatchError, ValueError) as exc:
            raise BridgeError(f"cannot fetch {cid}: {exc}") from exc
        try:
            bundle = load_untrusted(data)
        except BundleError as exc:
            raise BridgeError(f"content {cid} is not a valid policy bundle: {exc}") from exc
        except Exception as exc:  # no file may end in anything but a refusal
            raise BridgeError(f"content {cid} is not a valid policy bundle ({type(exc).__name__})") from exc
        path = self.cache_dir / f"{cid}.safetensors"
        # Write then rename, so an agent never reads a half-written file.
        with tempfile.NamedTemporaryFile(dir=self.cache_dir, delete=False, suffix=".part") as tmp:
            tmp.write(data)
        os.replace(tmp.name, path)
        return path, bundle.manifest

    def review(self, allocation_id: int, cid: str, score: float) -> str:
        """Review an allocation (``allocation_id``, or the latest one of ``cid`` via this bridge).

        Returns the transaction hash.

        Raises:
            BridgeError: no such allocation, a score outside [0, 1], or the registry refused.
        """
        if not (math.isfinite(score) and 0.0 <= score <= 1.0):
            raise BridgeError(f"score must be in [0, 1], got {score}")
        if not allocation_id:
            if cid not in self.allocations:
                raise BridgeError(f"no allocation of {cid!r} made through this bridge; give allocation_id")
            allocation_id = self.allocations[cid]
        try:
            result = self.registry.review(int(allocation_id), float(score))
        except (ValueError, RuntimeError) as exc:
            raise BridgeError(f"registry refused the review: {exc}") from exc
        return str(result.tx_hash)


def connect_registry(
    chain: str,
    content: str,
    users_manager: str = "",
    models_manager: str = "",
    private_key_file: str = "",
    account: int = 0,
) -> Any:
    """A :class:`medc_registry.Registry` from the bridge's connection parameters, a spec of
    medc_registry.home with every endpoint on loopback.

    ``chain="embedded"`` starts an in-process chain with fresh contracts (demos and tests).
    Otherwise ``chain`` is a JSON-RPC URL on this machine, the contract addresses are required,
    and the signing keys are read from ``private_key_file`` (never passed as a parameter, which
    any node of the graph could read); ``account`` indexes them.

    Raises:
        BridgeError: a missing or non-loopback endpoint, a missing key file, a node that does not
        answer, contracts that are not on the chain, or an account without a key.
    """
    from medc_registry.home import RegistryHomeError, spec_settings
    from medc_registry.registry import Registry

    try:
        settings = spec_settings(chain, content, users_manager, models_manager, private_key_file,
                                 loopback_only=True)
        return Registry.from_settings(settings, account)
    except (RegistryHomeError, ValueError) as exc:  # ValueError: an account it has no key for
        raise BridgeError(str(exc)) from None


def _declare_parameters(node: Any) -> tuple[tuple[str, str | None], dict[str, Any], str]:
    """Declare the bridge node's parameters: ((the team's namespace, the one names are built with:
    None = relative; medc_common.contract.team_namespace), :func:`connect_registry` keyword
    arguments, cache folder or "").

    Raises:
        BridgeError: a namespace parameter that is invalid or contradicts the node's namespace.
    """
    from medc_common import contract
    from medc_common.params import declare

    p = lambda *a, **k: declare(node, *a, **k)  # noqa: E731
    namespace = p("namespace", "", contract.NAMESPACE_HELP, True)
    connection = {
        "chain": p(
            "chain", "embedded", "'embedded' (in-process test chain) or a JSON-RPC URL on loopback", True
        ),
        "content": p("content", "", "Content store: a local folder, or an IPFS API URL on loopback", True),
        "users_manager": p("users_manager", "", "UsersManager contract address (JSON-RPC chain)", True),
        "models_manager": p("models_manager", "", "ModelsManager contract address (JSON-RPC chain)", True),
        "private_key_file": p("private_key_file", "", "File holding the bridge account's private key", True),
        "account": p("account", 0, "Signing account index: of the embedded chain's funded accounts, "
                     "or of the keys in private_key_file", True),
    }
    cache = p("cache_dir", "", "Folder for verified bundles (default: a new temporary folder)", True)
    try:
        names = contract.team_namespace(node.get_namespace(), namespace)
    except ValueError as exc:
        raise BridgeError(str(exc)) from None
    return names, connection, cache


def _allocations_answer(res: Any, allocs: list[Any]) -> Any:
    """Fill a RequestExperts response with the allocations made."""
    res.ok = True
    res.message = f"{len(allocs)} expert(s) allocated"
    res.allocation_ids = [int(a.allocation_id) for a in allocs]
    res.model_ids = [int(a.model_id) for a in allocs]
    res.cids = [a.cid for a in allocs]
    res.qos = [float(a.qos) for a in allocs]
    res.descriptions = [a.model.description for a in allocs]
    res.price_wei = str(sum(int(a.price_wei) for a in allocs))
    return res


class TempFolders:
    """Temporary folders a bridge node makes for itself (no ``cache_dir``, no ``content``): its
    bundle cache and its content store, removed when the node is destroyed."""

    def __init__(self) -> None:
        self.paths: list[str] = []

    def make(self, prefix: str) -> str:
        self.paths.append(tempfile.mkdtemp(prefix=prefix))
        return self.paths[-1]

    def remove(self) -> None:
        while self.paths:
            shutil.rmtree(self.paths.pop(), ignore_errors=True)


def bridge_summary(bridge: RegistryBridge, served: Counter) -> dict[str, str]:
    """The values of the bridge's heartbeat: where it caches bundles, how many it holds, the
    allocations it made, and the calls each service served and refused."""
    services = ("request_experts", "fetch_bundle", "submit_review")
    return {"cache_dir": str(bridge.cache_dir),
            "bundles_cached": str(sum(1 for _ in bridge.cache_dir.glob("*.safetensors"))),
            "allocations": str(len(bridge.allocations)),
            **{s: str(served[s]) for s in services},
            **{f"{s}_refused": str(served[f"{s}_refused"]) for s in services}}


def bridge_node_class():
    """The BridgeNode class (built on first use: it needs medc_interfaces importable)."""
    from medc_common import contract
    from medc_common.health import Health
    from medc_interfaces.srv import FetchBundle, RequestExperts, SubmitReview
    from rclpy.node import Node
    from std_msgs.msg import String

    class BridgeNode(Node):
        """ROS services over a :class:`RegistryBridge` (see the module docstring)."""

        def __init__(self, registry: Any = None, node_name: str = "medc_bridge", **kwargs: Any) -> None:
            kwargs.setdefault("namespace", contract.DEFAULT_NAMESPACE)
            super().__init__(node_name, **kwargs)
            (self.namespace_, self.names_ns), connection, cache = _declare_parameters(self)
            # No cache_dir (no content store): a temporary folder of this node's own for it,
            # removed again by destroy_node.
            self._own_dirs = TempFolders()
            try:
                if registry is None:
                    if not connection["content"]:
                        connection["content"] = self._own_dirs.make("medc-store-")
                    registry = connect_registry(**connection)
                self.bridge = RegistryBridge(registry, cache or self._own_dirs.make("medc-bundles-"))
            except BaseException:
                self._own_dirs.remove()
                raise
            for srv_type, name, handler in ((RequestExperts, "request_experts", self._on_request),
                                            (FetchBundle, "fetch_bundle", self._on_fetch),
                                            (SubmitReview, "submit_review", self._on_review)):
                self.create_service(srv_type, contract.registry_service(self.names_ns, name), handler)
            self._policy_pubs: dict[str, Any] = {}
            self._String = String
            #: Calls served and refused, per service (the heartbeat's values).
            self.served: Counter[str] = Counter()
            self.health = Health(self, "registry", lambda: bridge_summary(self.bridge, self.served))
            self.get_logger().info(
                f"registry bridge on {contract.registry_service(self.namespace_, 'fetch_bundle')} (and "
                f"request_experts, submit_review), caching bundles in {self.bridge.cache_dir}"
            )

        def destroy_node(self) -> None:
            super().destroy_node()
            self._own_dirs.remove()

        def _policy_pub(self, agent_id: str):
            if agent_id not in self._policy_pubs:
                self._policy_pubs[agent_id] = self.create_publisher(
                    self._String, contract.policy_topic(self.names_ns, agent_id), contract.LATCHED_QOS
                )
            return self._policy_pubs[agent_id]

        def _refuse(self, res, service: str, reason: str):
            res.ok, res.message = False, printable(reason, 2000)
            self.served[f"{service}_refused"] += 1
            self.get_logger().warning(f"{service} refused: {res.message}")
            return res

        def _failure(self, exc: Exception) -> str:
            """A refusal's reason: a BridgeError's message; any other exception (a fault of the chain
            node, the content store or this code) as an internal error, so no answer from outside
            ends the node."""
            return str(exc) if isinstance(exc, BridgeError) else f"internal error ({type(exc).__name__})"

        def _on_request(self, req, res):
            try:
                allocs = self.bridge.request(req.application, req.requirements_json, req.weights_json,
                                             req.count, req.min_model_reputation, req.min_owner_reputation)
            except Exception as exc:  # BridgeError, or anything at all: refuse and keep serving
                return self._refuse(res, "request_experts", self._failure(exc))
            self.served["request_experts"] += 1
            return _allocations_answer(res, allocs)

        def _on_fetch(self, req, res):
            try:
                ids = list(req.agent_ids)
                for agent_id in ids:
                    if not contract.AGENT_ID_PATTERN.match(agent_id):
                        raise BridgeError(f"unknown agent id {agent_id!r}: expected agent_<i>")
                path, manifest = self.bridge.fetch(req.cid)
            except Exception as exc:  # BridgeError, or anything at all: refuse and keep serving
                return self._refuse(res, "fetch_bundle", self._failure(exc))
            self.served["fetch_bundle"] += 1
            for agent_id in ids:
                self._policy_pub(agent_id).publish(self._String(data=str(path)))
            res.ok, res.path, res.manifest_json = True, str(path), json.dumps(manifest)
            res.message = f"verified {req.cid}" + (f", handed to {', '.join(ids)}" if ids else "")
            self.get_logger().info(res.message)
            return res

        def _on_review(self, req, res):
            try:
                res.tx_hash = self.bridge.review(int(req.allocation_id), req.cid, float(req.score))
            except Exception as exc:  # BridgeError, or anything at all: refuse and keep serving
                return self._refuse(res, "submit_review", self._failure(exc))
            self.served["submit_review"] += 1
            res.ok, res.message = True, "review recorded"
            return res

    return BridgeNode


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-bridge``: serve the registry to the graph until Ctrl-C; ``--help`` lists
    its parameters and exits 0 without starting it."""
    from medc_common.cli_help import print_node_help, wants_help

    if wants_help(argv):
        return print_node_help(
            "medc-bridge", "The registry bridge node: the model registry's services (request_experts, "
                           "fetch_bundle, submit_review) on the ROS graph.", ["medc_registry.bridge_node"],
            "medc-bridge --ros-args -p chain:=embedded -p content:=/tmp/store")
    require_interfaces()
    from medc_common.executors import run_node
    from rclpy.executors import SingleThreadedExecutor

    return run_node("medc-bridge", argv, lambda: bridge_node_class()(), errors=(BridgeError,),
                    executor_factory=SingleThreadedExecutor)


if __name__ == "__main__":
    sys.exit(main())
