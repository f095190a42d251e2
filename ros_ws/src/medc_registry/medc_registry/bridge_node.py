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

Money: any node of the graph may call request_experts, so the bridge pays only under two limits.
Per expert, the call's ``max_price_wei``, or by default 10 times the cheapest non-zero price among
the experts the request could get (medc_registry.ranker); in all, the ``budget`` parameter (ETH,
or NNNwei; :data:`DEFAULT_BUDGET`) over the node's life: a request whose quote is over what is left
of it is refused before anything is signed. Text parameters (the contract addresses above all)
are read as the text given: ``-p users_manager:=0x5FbD…`` is an address, not the number ROS's
parameter parser makes of it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import tempfile
import threading
from collections import Counter
from pathlib import Path
from typing import Any

from medc_common import contract
from medc_common.executors import ros_argument_values
from medc_common.health import Health
from medc_common.ros_env import require_interfaces
from medc_training.outfiles import check_output_folder
from medc_training.untrusted import UntrustedJSONError, parse_json, printable
from rclpy.node import Node
from std_msgs.msg import String

from medc_registry.records import format_eth

#: Longest ``requirements_json`` / ``weights_json`` a service call may carry (8 features of a
#: short name each fit in a few hundred characters).
MAX_REQUEST_JSON_CHARS = 4096
#: The most a bridge pays for experts in all, over its life, unless its ``budget`` parameter
#: says otherwise (ETH, or NNNwei).
DEFAULT_BUDGET = "0.01"


class BridgeError(ValueError):
    """A bridge request that cannot be served; the message says why."""


class RegistryBridge:
    """The registry operations the bridge serves, over one :class:`medc_registry.Registry`."""

    def __init__(
        self, registry: Any, cache_dir: str | os.PathLike[str], budget_wei: int | None = None
    ) -> None:
        self.registry = registry
        try:  # a file, a device or a name too long: refused before anything is served
            self.cache_dir = check_output_folder(cache_dir)
            self.cache_dir.mkdir(parents=True, exist_ok=True)
        except ValueError as exc:
            raise BridgeError(f"cache_dir: {exc}") from None
        except OSError as exc:
            raise BridgeError(f"cache_dir {printable(os.fspath(cache_dir), 200)}: {exc.strerror}") from None
        #: Latest allocation id per CID requested through this bridge (for reviews by CID).
        self.allocations: dict[str, int] = {}
        #: The most this bridge pays in all (wei), and what it has paid or may have paid so far.
        self.budget_wei = parse_budget(DEFAULT_BUDGET) if budget_wei is None else budget_wei
        self.spent_wei = 0
        self._money = threading.Lock()

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
        max_price_wei: str = "",
    ) -> list[Any]:
        """Request up to ``count`` experts; returns the registry's allocations, best first.

        Each expert costs at most ``max_price_wei`` (decimal wei; "" = the registry's default
        limit), and the request at most what is left of :attr:`budget_wei`: a dearer quote is
        refused before anything is signed. One request at a time, so two calls can never both
        spend what is left.

        Raises:
            BridgeError: malformed requirements, weights or price limit, a quote over the budget,
            or the registry refused.
        """
        from medc_registry.chain import ContractRevert
        from medc_registry.journal import OverBudget

        requirements = self._json_object(requirements_json, "requirements_json")
        if requirements is None:
            raise BridgeError('requirements_json is required, e.g. {"agents": 3, "walls": 2}')
        weights = self._json_object(weights_json, "weights_json")
        max_price = parse_wei_text(max_price_wei, "max_price_wei")
        with self._money:
            left = max(0, self.budget_wei - self.spent_wei)
            quoted: list[int] = []
            try:
                allocs = self.registry.request_models(
                    application,
                    requirements,
                    weights,
                    count=max(1, int(count)),
                    min_model_rep=min_model_rep,
                    min_owner_rep=min_owner_rep,
                    max_price=max_price,
                    max_total=left,
                    on_quote=lambda ranking: quoted.append(ranking.price_wei),
                )
            except OverBudget as exc:
                raise BridgeError(
                    f"over this bridge's budget: {format_eth(left)} left of {format_eth(self.budget_wei)} "
                    f"(parameter budget); {exc}") from exc
            except (ValueError, ContractRevert) as exc:  # refused, or reverted: nothing was paid
                raise BridgeError(f"registry refused the request: {exc}") from exc
            except BaseException as exc:
                # A payment may have gone out (an answer lost after sending): counted as spent.
                self.spent_wei += sum(quoted)
                if isinstance(exc, RuntimeError):  # ChainError
                    raise BridgeError(f"registry refused the request: {exc}") from exc
                raise
            self.spent_wei += sum(int(a.price_wei) for a in allocs if not a.replayed)
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
        from medc_registry.files import write_atomic

        path = self.cache_dir / f"{cid}.safetensors"
        # A fresh temporary file renamed into place: an agent never reads a half-written file, a
        # failed write leaves nothing behind, and a link planted at the name is replaced.
        write_atomic(path, data, mode=0o644)
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


def parse_wei_text(text: str, what: str) -> int | None:
    """A whole number of wei written in decimal digits (as a service field carries it), None for
    ""; BridgeError for anything else."""
    if not isinstance(text, str) or not text.strip():
        return None
    value = text.strip()
    if len(value) > 40 or not value.isascii() or not value.isdigit() or int(value) >= 2**128:
        raise BridgeError(f"{what} must be a whole number of wei in decimal digits below 2**128, e.g. "
                          '"1000000000000000" for 0.001 ETH, or "" for the default; got '
                          f"{printable(value, 60)!r}")
    return int(value)


def parse_budget(text: str) -> int:
    """The ``budget`` parameter (ETH, e.g. ``0.01``, or ``NNNwei``) in wei; BridgeError if it is
    not an amount."""
    from medc_registry.cli import CliError, parse_eth

    try:
        return parse_eth(str(text), "budget")
    except CliError as exc:
        raise BridgeError(str(exc)) from None


def command_line_value(command_line: list[str], node_name: str, name: str) -> str | None:
    """The text given for parameter ``name`` on a ROS command line (``--ros-args -p name:=TEXT``,
    or ``-p node_name:name:=TEXT``), the last one given; None when none is."""
    found = None
    for _, text in ros_argument_values(list(command_line), ("-p", "--param")):
        key, sep, value = text.partition(":=")
        if not sep:
            continue
        target, _, key = key.rpartition(":")
        if key == name and target.rsplit("/", 1)[-1] in ("", node_name):
            found = value
    return found


def declare_text(node: Any, name: str, default: str, description: str,
                 command_line: list[str] | None) -> str:
    """Declare a text parameter and return it as the text given. ROS's parameter parser reads
    ``0x5FbD…`` (an address) as a number and ``true`` as a boolean; such a value is taken back as
    it was written on ``command_line`` (``-p name:=TEXT``), and refused clearly when it came from
    elsewhere (a params file: quote it there)."""
    from rcl_interfaces.msg import ParameterDescriptor

    node.declare_parameter(name, default, ParameterDescriptor(
        description=description, read_only=True, dynamic_typing=True))
    value = node.get_parameter(name).value
    if isinstance(value, str):
        return value
    text = command_line_value(command_line or [], node.get_name(), name)
    if text is not None:
        return text
    raise BridgeError(
        f"parameter {name} must be text, but ROS read it as the {type(value).__name__} {value!r} (it reads "
        f"0x..., digits and true/false so): quote it, e.g. {name}: \"0x5FbD...\" in a params file"
    )


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
        BridgeError: a missing or non-loopback endpoint, a missing key file, a content store
        folder that cannot be one, a node that does not answer, contracts that are not on the
        chain, or an account without a key.
    """
    from medc_registry.content import ContentStoreError
    from medc_registry.home import RegistryHomeError, spec_settings
    from medc_registry.registry import Registry

    try:
        settings = spec_settings(chain, content, users_manager, models_manager, private_key_file,
                                 loopback_only=True)
        return Registry.from_settings(settings, account)
    except (RegistryHomeError, ContentStoreError, ValueError) as exc:  # ValueError: an account with no key
        raise BridgeError(str(exc)) from None


def _declare_parameters(
    node: Any, command_line: list[str] | None = None
) -> tuple[tuple[str, str | None], dict[str, Any], str, int]:
    """Declare the bridge node's parameters: ((the team's namespace, the one names are built with:
    None = relative; medc_common.contract.team_namespace), :func:`connect_registry` keyword
    arguments, cache folder or "", budget in wei). Text parameters are read as the text given on
    ``command_line`` (:func:`declare_text`).

    Raises:
        BridgeError: a namespace parameter that is invalid or contradicts the node's namespace, a
        text parameter ROS read as a number and no command line gives, or a budget that is not
        an amount.
    """
    from medc_common.params import declare

    def p(name: str, default: Any, description: str, read_only: bool = False) -> Any:
        if isinstance(default, str):
            return declare_text(node, name, default, description, command_line)
        return declare(node, name, default, description, read_only)

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
    budget = parse_budget(p("budget", DEFAULT_BUDGET, "The most the bridge pays for experts in all, over "
                            "its life, in ETH (e.g. 0.01) or NNNwei; a request whose quote is over what "
                            "is left is refused before anything is paid", True))
    try:
        names = contract.team_namespace(node.get_namespace(), namespace)
    except ValueError as exc:
        raise BridgeError(str(exc)) from None
    return names, connection, cache, budget


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
    allocations it made, its budget and what it spent (wei), and the calls each service served
    and refused."""
    services = ("request_experts", "fetch_bundle", "submit_review")
    return {"cache_dir": str(bridge.cache_dir),
            "bundles_cached": str(sum(1 for _ in bridge.cache_dir.glob("*.safetensors"))),
            "allocations": str(len(bridge.allocations)),
            "budget_wei": str(bridge.budget_wei), "spent_wei": str(bridge.spent_wei),
            **{s: str(served[s]) for s in services},
            **{f"{s}_refused": str(served[f"{s}_refused"]) for s in services}}


class BridgeNode(Node):
    """ROS services over a :class:`RegistryBridge` (see the module docstring)."""

    def __init__(self, registry: Any = None, node_name: str = "medc_bridge",
                 command_line: list[str] | None = None, **kwargs: Any) -> None:
        """``command_line``: the process's arguments (``--ros-args`` among them), where text
        parameters ROS's parser turned into numbers are read back as written."""
        from medc_interfaces.srv import FetchBundle, RequestExperts, SubmitReview

        kwargs.setdefault("namespace", contract.DEFAULT_NAMESPACE)
        super().__init__(node_name, **kwargs)
        (self.namespace_, self.names_ns), connection, cache, budget = _declare_parameters(
            self, command_line)
        # No cache_dir (no content store): a temporary folder of this node's own for it,
        # removed again by destroy_node.
        self._own_dirs = TempFolders()
        try:
            if registry is None:
                if not connection["content"]:
                    connection["content"] = self._own_dirs.make("medc-store-")
                registry = connect_registry(**connection)
            self.bridge = RegistryBridge(registry, cache or self._own_dirs.make("medc-bundles-"), budget)
        except BaseException:
            self._own_dirs.remove()
            raise
        for srv_type, name, handler in ((RequestExperts, "request_experts", self._on_request),
                                        (FetchBundle, "fetch_bundle", self._on_fetch),
                                        (SubmitReview, "submit_review", self._on_review)):
            self.create_service(srv_type, contract.registry_service(self.names_ns, name), handler)
        self._policy_pubs: dict[str, Any] = {}
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
                String, contract.policy_topic(self.names_ns, agent_id), contract.LATCHED_QOS
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
                                         req.count, req.min_model_reputation, req.min_owner_reputation,
                                         req.max_price_wei)
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
            self._policy_pub(agent_id).publish(String(data=str(path)))
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


def bridge_node_class() -> type[BridgeNode]:
    """The BridgeNode class (its services' types are imported when a node is made: they need
    medc_interfaces importable, which main checks first)."""
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

    command_line = list(sys.argv if argv is None else argv)
    return run_node("medc-bridge", argv, lambda: bridge_node_class()(command_line=command_line),
                    errors=(BridgeError,),
                    executor_factory=SingleThreadedExecutor)


if __name__ == "__main__":
    sys.exit(main())
