"""The registry facade: the paper's time sequence over one chain client and one content store.

Typical use (embedded chain and a local content store, one call)::

    from medc_registry import Registry
    reg = Registry.embedded("/tmp/medc-store")          # deploys both contracts
    alice, bob = reg.as_user(1), reg.as_user(2)
    alice.register_user(); bob.register_user()
    m = alice.share_model(bundle_bytes, "target_localization", {"agents": 1, "walls": 3}, price=10**15)
    allocs = bob.request_models("target_localization", {"agents": 3, "walls": 2}, count=2)
    data = bob.fetch(allocs[0].cid)                      # verified against the CID
    bob.review(allocs[0].allocation_id, 0.9)
    alice.withdraw()

Amounts are wei (ints); reputations, reviews, weights and QoS are floats in Python and fixed
point (1e18 = 1.0) on chain. Environment features are non-negative integers, given as a mapping
(feature name -> value; stored in sorted name order, the names recorded in the model's description)
or as a sequence in the application's order.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from eth_utils import to_checksum_address
from medc_training.qos import fixed_weights, from_fixed, is_exact, to_fixed
from web3.logs import DISCARD

from .chain import ChainClient, ChainError, ContractRevert, TxResult
from .content import ContentStore
from .home import (
    EMBEDDED,
    HOME_DEADLINE,
    STATE_FILE,
    RegistryHomeError,
    RegistrySettings,
    home_settings,
    spec_settings,
)

MAX_FEATURES = 8
#: Most candidate models one allocateModels call examines (the contract's MAX_CANDIDATES).
MAX_CANDIDATES = 256
#: Most models one request may ask for (so a ranking page always has room for new candidates).
MAX_COUNT = MAX_CANDIDATES // 2
_UINT32 = 2**32 - 1

Features = Mapping[str, int] | Sequence[int]


def format_eth(wei: int) -> str:
    """Wei in human units (ETH with up to 6 decimals)."""
    return f"{wei / 10**18:.6f}".rstrip("0").rstrip(".") + " ETH"


@dataclass(frozen=True)
class UserInfo:
    """A user's record in the Users Manager."""

    address: str
    registered: bool
    reputation: float
    alloc_count: int
    total_review: float


@dataclass(frozen=True)
class SharedModel:
    """A model as recorded in the Models Manager."""

    model_id: int
    owner: str
    application: str
    cid: str
    description: str
    features: tuple[str, ...]
    env: tuple[int, ...]
    price_wei: int
    reputation: float
    alloc_count: int
    total_review: float

    @property
    def env_features(self) -> dict[str, int] | tuple[int, ...]:
        """The environment as a name -> value dict when names are known."""
        if self.features and len(self.features) == len(self.env):
            return dict(zip(self.features, self.env))
        return self.env


@dataclass(frozen=True)
class Allocation:
    """One model allocated to a requester (``allocation_id`` is what to review)."""

    allocation_id: int
    model: SharedModel
    qos: float  # math.inf for an exact environment match (D_m = 0)
    distance: float  # D_m in feature units
    price_wei: int
    requester: str
    #: The request's idempotency key (0x + 64 hex digits).
    request_id: str = ""
    #: True when the request had been paid by an earlier attempt and this is its allocation.
    replayed: bool = False

    @property
    def model_id(self) -> int:
        return self.model.model_id

    @property
    def cid(self) -> str:
        return self.model.cid

    @property
    def owner(self) -> str:
        return self.model.owner


class PendingRequests:
    """Paid requests sent but not yet confirmed: one JSON file (``path``), or memory (``None``).

    A record is written (and fsynced) *before* its transaction is sent, with the request id, the
    signed transaction and its hash, so a run that lost the node's answer can be resolved by the
    next one instead of paying again.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self._memory: dict[str, dict[str, Any]] = {}

    def __repr__(self) -> str:
        return f"PendingRequests({str(self.path) if self.path else 'in memory'})"

    def load(self) -> dict[str, dict[str, Any]]:
        """All records, keyed ``account:request_id``."""
        if self.path is None:
            return dict(self._memory)
        if not self.path.is_file():
            return {}
        return json.loads(self.path.read_text())

    def _save(self, records: dict[str, dict[str, Any]]) -> None:
        if self.path is None:
            self._memory = records
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w") as fh:
            fh.write(json.dumps(records, indent=1, sort_keys=True) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)

    @staticmethod
    def _key(record: dict[str, Any]) -> str:
        return f"{record['account']}:{record['request_id']}"

    def put(self, record: dict[str, Any]) -> None:
        """Add or replace ``record`` (durably: written and fsynced before its transaction is sent)."""
        records = self.load()
        records[self._key(record)] = record
        self._save(records)

    def drop(self, record: dict[str, Any]) -> None:
        """Forget a resolved request."""
        records = self.load()
        if records.pop(self._key(record), None) is not None:
            self._save(records)

    def find(
        self, account: str, fingerprint: str | None = None, request_id: str | None = None
    ) -> dict[str, Any] | None:
        """``account``'s pending record with that request id, or else for the same request, if any."""
        for record in self.load().values():
            if record["account"] != account:
                continue
            if request_id is not None and record["request_id"] == request_id:
                return record
            if request_id is None and record["fingerprint"] == fingerprint:
                return record
        return None


def request_id_from(value: str | bytes | None) -> bytes:
    """A 32-byte request id: ``0x`` + 64 hex digits as is, other text hashed, None a random one."""
    if value is None:
        return os.urandom(32)
    if isinstance(value, bytes | bytearray):
        if len(value) != 32:
            raise ValueError(f"a request id given as bytes must be 32 bytes, got {len(value)}")
        rid = bytes(value)
    elif isinstance(value, str) and value.strip():
        text = value.strip()
        if text.lower().startswith("0x") and len(text) == 66:
            try:
                rid = bytes.fromhex(text[2:])
            except ValueError:
                raise ValueError(f"request id {value!r} is not 0x + 64 hex digits") from None
        else:
            rid = hashlib.sha256(text.encode()).digest()
    else:
        raise ValueError(f"a request id must be a non-empty string or 32 bytes, got {value!r}")
    if rid == bytes(32):
        raise ValueError("the request id must not be zero")
    return rid


@dataclass
class Deployment:
    """Where the two contracts live."""

    users: str
    models: str
    gas: dict[str, int] = field(default_factory=dict)


def deploy_contracts(chain: ChainClient, sender: int | str = 0) -> Deployment:
    """Deploy the Users Manager and the Models Manager and bind them."""
    umc = chain.deploy("UsersManager", sender=sender)
    mmc = chain.deploy("ModelsManager", umc.contract_address, sender=sender)
    bind = chain.transact(
        chain.contract("UsersManager", umc.contract_address).functions.setManager(mmc.contract_address),
        sender=sender,
    )
    return Deployment(
        umc.contract_address,
        mmc.contract_address,
        {"UsersManager": umc.gas_used, "ModelsManager": mmc.gas_used, "setManager": bind.gas_used},
    )


class Registry:
    """The MEDC registry for one signing account (see the module docstring)."""

    def __init__(
        self, chain: ChainClient, store: ContentStore, deployment: Deployment, account: int | str = 0
    ) -> None:
        self.chain = chain
        self.store = store
        self.deployment = deployment
        self._account = chain.account(account)
        #: Where paid requests are recorded before they are sent (set by the CLI to the home).
        self.pending = PendingRequests()
        self.users = chain.contract("UsersManager", deployment.users)
        self._feature_cache: dict[str, tuple[str, ...]] = {}
        #: The last transaction this registry sent (hash, gasUsed, receipt), e.g. for gas figures.
        self.last_tx: TxResult | None = None
        self.models = chain.contract("ModelsManager", deployment.models)

    # ------------------------------------------------------------ construction
    @classmethod
    def embedded(cls, store_dir: str | None = None, account: int | str = 0) -> Registry:
        """In-process eth-tester chain with fresh contracts and a local content store.

        ``store_dir`` defaults to a new temporary directory. Nothing on the chain persists.
        """
        return cls.from_settings(spec_settings(EMBEDDED, str(store_dir or "")), account)

    @classmethod
    def from_settings(
        cls, settings: RegistrySettings, account: int | str = 0, deadline: float | None = None
    ) -> Registry:
        """The registry ``settings`` describe (medc_registry.home: a home folder or a spec).

        An embedded chain gets fresh contracts; on a JSON-RPC chain the recorded Models Manager
        must be there. ``deadline``: total seconds of one chain call (default: the client's).

        Raises:
            RegistryHomeError: the node does not answer, there are no signing keys, or the
            contracts are not on the chain.
            ValueError: ``account`` is not one of the signing accounts.
        """
        store = settings.open_store()
        chain = settings.open_chain(deadline)
        if settings.embedded:
            deployment = deploy_contracts(chain)
        else:
            deployment = Deployment(settings.users_manager, settings.models_manager)
            if not chain.has_code(deployment.models):
                fix = (f"remove {settings.home / STATE_FILE} and run `medc-registry start` again"
                       if settings.home is not None else "check the models_manager address")
                raise RegistryHomeError(
                    f"no Models Manager contract at {deployment.models} on {settings.chain}: the chain's "
                    f"state was lost or the address is wrong; {fix}"
                )
        reg = cls(chain, store, deployment, account)
        reg.pending = PendingRequests(settings.pending_file)
        return reg

    @classmethod
    def from_home(
        cls,
        home: str | os.PathLike[str] | None = None,
        account: int | str = 0,
        deadline: float = HOME_DEADLINE,
    ) -> Registry:
        """The registry recorded by ``medc-registry start`` / ``deploy`` in ``home``.

        ``home`` defaults to ``$MEDC_HOME`` or ``./.medc``. Raises ``RegistryHomeError`` (a
        ``RuntimeError``) with the command to run when no chain is configured there or its node
        does not answer.
        """
        return cls.from_settings(home_settings(home), account, deadline)

    def as_user(self, account: int | str) -> Registry:
        """The same registry acting as another signing account (index or address)."""
        other = Registry(self.chain, self.store, self.deployment, account)
        other._feature_cache = self._feature_cache  # per application, fixed once set on chain
        other.pending = self.pending
        return other

    @property
    def address(self) -> str:
        """This registry's signing address."""
        return self._account.address

    def _tx(self, fn: Any, value: int = 0) -> TxResult:
        self.last_tx = self.chain.transact(fn, sender=self.address, value=value)
        return self.last_tx

    # ------------------------------------------------------------ users
    def register_user(self) -> TxResult:
        """Register this account (reputation starts at 0.5)."""
        return self._tx(self.users.functions.addUser())

    def user(self, address: str | None = None) -> UserInfo:
        """A user's record (this account by default)."""
        addr = to_checksum_address(address or self.address)
        reg, rep, count, total = self.chain.call(self.users.functions.getUser(addr))
        return UserInfo(addr, reg, from_fixed(rep), count, from_fixed(total))

    # ------------------------------------------------------------ models
    def share_model(
        self,
        bundle: bytes,
        application: str,
        env_features: Features,
        price: int,
        description: str | Mapping[str, Any] | None = None,
        cid_version: int = 0,
    ) -> SharedModel:
        """Upload ``bundle`` to the content store and register it (paper: addModel).

        Args:
            bundle: the model file's bytes (a policy bundle is data to the registry).
            application: e.g. ``"target_localization"``.
            env_features: environment features (mapping name -> int, or ints in the app's order).
            price: wei a requester pays each time the model is allocated.
            description: extra text or JSON-able details stored with the model.
            cid_version: 0 (``ipfs add``) or 1 (``ipfs add --cid-version=1``).
        """
        if not isinstance(bundle, bytes | bytearray) or not bundle:
            raise ValueError("bundle must be non-empty bytes (the model file's content)")
        _check_app(application)
        if not isinstance(price, int) or price < 0 or price >= 2**128:
            raise ValueError(f"price must be an integer number of wei in [0, 2**128), got {price!r}")
        names, values = _features(env_features)
        existing = self._feature_names(application)
        if existing is not None and names and existing and names != existing:
            raise ValueError(f"{application!r} models use features {list(existing)}, got {list(names)}")
        desc: dict[str, Any] = {}
        if names:
            desc["features"] = list(names)
        desc.update(bundle_summary(bytes(bundle)))
        if isinstance(description, Mapping):
            desc.update(description)
        elif description:
            desc["text"] = str(description)
        cid = self.store.add(bytes(bundle), cid_version)
        self.store.pin(cid)
        text = json.dumps(desc, separators=(",", ":"), sort_keys=True) if desc else ""
        result = self._tx(self.models.functions.addModel(application, cid, text, list(values), price))
        event = self.models.events.ModelAdded().process_receipt(result.receipt, errors=DISCARD)[0]
        return self.model(event["args"]["modelId"])

    def model(self, model_id: int) -> SharedModel:
        """Model ``model_id`` (ContractRevert ``UnknownModel`` if there is none)."""
        owner, app_id, env, price, rep, count, total = self.chain.call(
            self.models.functions.getModel(model_id)
        )
        cid, description = self.chain.call(self.models.functions.getModelText(model_id))
        application = self.chain.call(self.models.functions.applicationName(app_id))
        names: tuple[str, ...] = ()
        if description:
            try:
                names = tuple(json.loads(description).get("features", ()))
            except (ValueError, AttributeError):
                names = ()
        return SharedModel(
            model_id,
            owner,
            application,
            cid,
            description,
            names,
            tuple(env),
            price,
            from_fixed(rep),
            count,
            from_fixed(total),
        )

    def model_count(self) -> int:
        """Number of shared models."""
        return self.chain.call(self.models.functions.modelCount())

    def list_models(self, application: str | None = None) -> list[SharedModel]:
        """All shared models (of ``application`` when given)."""
        out = [self.model(i) for i in range(self.model_count())]
        return [m for m in out if application is None or m.application == application]

    def _feature_names(self, application: str) -> tuple[str, ...] | None:
        """Feature names of ``application`` (fixed by its first model), None if it has none."""
        if application in self._feature_cache:
            return self._feature_cache[application]
        for i in range(self.model_count()):
            m = self.model(i)
            if m.application == application:
                self._feature_cache[application] = m.features
                return m.features
        return None

    # ------------------------------------------------------------ allocation
    def _allocate_args(
        self,
        application: str,
        requirements: Features,
        weights: Features | None,
        count: int,
        min_model_rep: float,
        min_owner_rep: float,
    ) -> tuple:
        _check_app(application)
        if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_COUNT:
            raise ValueError(f"count must be an integer from 1 to {MAX_COUNT}, got {count!r}")
        req_names, req = _features(requirements)
        expected = self._feature_names(application)
        if expected is None:
            raise ContractRevert("UnknownApplication", {"application": application})
        if req_names and expected and req_names != expected:
            raise ValueError(f"{application!r} models use features {list(expected)}, got {list(req_names)}")
        w: list[int] = []
        if weights is not None:
            w_names, w_raw = _weights(weights)
            if w_names and req_names and w_names != req_names:
                raise ValueError(f"weights name {list(w_names)}, requirements name {list(req_names)}")
            if len(w_raw) != len(req):
                raise ValueError(f"give one weight per feature ({len(req)}), got {len(w_raw)}")
            w = w_raw
        return (
            application,
            list(req),
            w,
            count,
            to_fixed(min_model_rep, "min_model_rep"),
            to_fixed(min_owner_rep, "min_owner_rep"),
        )

    def rank(
        self,
        application: str,
        requirements: Features,
        weights: Features | None = None,
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
    ) -> list[int]:
        """The ids of the best ``count`` eligible models for this account, best first (no transaction).

        The contract ranks: ``allocateModels`` is simulated (eth_call, free) on pages of the
        application's models, each page joined by the best ids so far, so the result is the
        contract's own greedy top ``count`` over all of them, however many there are.
        """
        args = self._allocate_args(application, requirements, weights, count, min_model_rep, min_owner_rep)
        return self._rank(args)[0]

    def _app_model_ids(self, application: str) -> list[int]:
        """The application's Models List (model ids in the order shared), from the contract's events."""
        added = self.chain._retry(
            lambda: self.models.events.ApplicationAdded().get_logs(from_block=0), "read the applications"
        )
        app_ids = [log["args"]["appId"] for log in added if log["args"]["application"] == application]
        if not app_ids:
            raise ContractRevert("UnknownApplication", {"application": application})
        logs = self.chain._retry(
            lambda: self.models.events.ModelAdded().get_logs(
                argument_filters={"appId": app_ids[0]}, from_block=0
            ),
            "read the application's models",
        )
        return sorted(log["args"]["modelId"] for log in logs)

    def _simulate(self, args: tuple, positions: list[int]) -> tuple[list[int], int]:
        """Model ids ``allocateModels`` would allocate from these positions of the application's
        Models List now, best first, and their price (an eth_call: nothing is sent)."""
        fn = self.models.functions.allocateModels(request_id_from(None), *args, sorted(positions))
        try:
            ids, _ = self.chain.call(fn, sender=self.address, value=0)
            return list(ids), 0
        except ContractRevert as exc:
            if exc.error != "InsufficientPayment":
                raise
            # The revert names the exact price of what would be allocated.
            required = exc.values["required"]
        ids, _ = self.chain.call(fn, sender=self.address, value=required)
        return list(ids), required

    def _rank(self, args: tuple) -> tuple[list[int], list[int], int]:
        """(best model ids, best first; their positions in the Models List; their total price)."""
        ids = self._app_model_ids(args[0])
        position = {model_id: pos for pos, model_id in enumerate(ids)}
        page = MAX_CANDIDATES - args[3]
        best: list[int] = []
        price = 0
        for start in range(0, len(ids), page):
            try:
                best, price = self._simulate(
                    args, [position[i] for i in best] + list(range(start, min(start + page, len(ids))))
                )
            except ContractRevert as exc:
                if exc.error != "NoEligibleModels":
                    raise
        if not best:
            raise ContractRevert("NoEligibleModels")
        return best, sorted(position[i] for i in best), price

    def quote(
        self,
        application: str,
        requirements: Features,
        weights: Features | None = None,
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
    ) -> tuple[list[int], int]:
        """Which models a request would get now and their total price in wei (no transaction)."""
        args = self._allocate_args(application, requirements, weights, count, min_model_rep, min_owner_rep)
        best, _positions, price = self._rank(args)
        return best, price

    def request_models(
        self,
        application: str,
        requirements: Features,
        weights: Features | None = None,
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
        payment: int | None = None,
        request_id: str | bytes | None = None,
    ) -> list[Allocation]:
        """Request up to ``count`` models (paper: allocateModels) and pay for them, exactly once.

        ``payment`` (wei) defaults to the exact price of what would be allocated (see :meth:`quote`);
        any overpayment is credited back and can be withdrawn. Returns the allocations best first.

        Idempotent: the request carries an id (``request_id``: ``0x`` + 64 hex digits, any other
        text is hashed; default random) that the contract records and refuses to pay twice. The
        id and the signed transaction are written to :attr:`pending` before sending; when the
        node's answer is lost, calling again with the same arguments (or the same ``request_id``)
        resolves that record: the original allocation if it was mined (``replayed=True``), else
        the same request is sent again, which the contract can only pay once.
        """
        args = self._allocate_args(application, requirements, weights, count, min_model_rep, min_owner_rep)
        if payment is not None and (isinstance(payment, bool) or not isinstance(payment, int) or payment < 0):
            raise ValueError(f"payment must be a non-negative integer number of wei, got {payment!r}")
        fingerprint = hashlib.sha256(
            json.dumps([self.address, list(args), payment], sort_keys=True).encode()
        ).hexdigest()
        rid = request_id_from(request_id) if request_id is not None else None
        record = self.pending.find(self.address, fingerprint, "0x" + rid.hex() if rid else None)
        if record is not None:
            return self._resolve(record)
        rid = rid or request_id_from(None)
        paid = self._paid(rid)
        if paid is not None:
            return paid
        _best, candidates, price = self._rank(args)
        if payment is None:
            payment = price
        fn = self.models.functions.allocateModels(rid, *args, candidates)
        signed = self.chain.sign(fn, self.address, payment)
        record = {
            "request_id": "0x" + rid.hex(),
            "account": self.address,
            "fingerprint": fingerprint,
            "args": [*args, candidates],
            "value": payment,
            "tx_hash": signed.tx_hash,
            "raw": "0x" + signed.raw.hex(),
            "nonce": signed.nonce,
            "created": time.time(),
        }
        self.pending.put(record)  # before sending: a lost answer is resolved by the next call
        return self._send(record, fn, signed.raw)

    def pending_requests(self) -> list[dict[str, Any]]:
        """This account's paid requests not confirmed yet (resolve one by requesting it again)."""
        return [r for r in self.pending.load().values() if r["account"] == self.address]

    def _send(self, record: dict[str, Any], fn: Any, raw: bytes) -> list[Allocation]:
        try:
            result = self.chain.send_raw(raw, fn=fn, sender=self.address, value=record["value"])
        except ContractRevert as exc:
            return self._settled(record, exc)
        except ChainError as exc:
            where = self.pending.path or "this Registry's pending requests (memory)"
            raise ChainError(
                f"{exc}. Request {record['request_id']} (transaction {record['tx_hash']}) is recorded "
                f"in {where}: run the same request again to resolve it; the contract pays a request id "
                "at most once, so re-running cannot pay twice"
            ) from None
        self.last_tx = result
        self.pending.drop(record)
        return self._allocations(result.receipt, record["request_id"], replayed=False)

    def _settled(self, record: dict[str, Any], exc: ContractRevert) -> list[Allocation]:
        """A request's transaction reverted: the earlier payment if that was why, else the revert."""
        self.pending.drop(record)
        if exc.error == "RequestAlreadyPaid":
            paid = self._paid(bytes.fromhex(record["request_id"][2:]))
            if paid is not None:
                return paid
        raise exc

    def _resolve(self, record: dict[str, Any]) -> list[Allocation]:
        """Finish a request recorded by an earlier call whose outcome was not seen."""
        rid = bytes.fromhex(record["request_id"][2:])
        fn = self.models.functions.allocateModels(rid, *record["args"])
        try:
            state = self.chain.lookup(record["tx_hash"], fn, self.address, record["value"])
        except ContractRevert as exc:
            return self._settled(record, exc)
        if isinstance(state, TxResult):
            self.pending.drop(record)
            return self._allocations(state.receipt, record["request_id"], replayed=True)
        paid = self._paid(rid)
        if paid is not None:
            self.pending.drop(record)
            return paid
        raw = bytes.fromhex(record["raw"][2:])
        if state == "unknown" and record["nonce"] < self.chain.pending_nonce(self.address):
            # The nonce went to another transaction, so the recorded one can never be mined:
            # sign the same request (same id) again; the contract still pays it at most once.
            signed = self.chain.sign(fn, self.address, record["value"])
            record = {
                **record,
                "tx_hash": signed.tx_hash,
                "raw": "0x" + signed.raw.hex(),
                "nonce": signed.nonce,
            }
            self.pending.put(record)
            raw = signed.raw
        return self._send(record, fn, raw)

    def _paid(self, rid: bytes) -> list[Allocation] | None:
        """The allocations of request ``rid`` if this account already paid it, else None.

        The contract checks a request id before anything else, so a simulated call with the id
        answers RequestAlreadyPaid(firstAllocationId) exactly when it was paid.
        """
        fn = self.models.functions.allocateModels(rid, "", [], [], 0, 0, 0, [])
        try:
            self.chain.call(fn, sender=self.address)
        except ContractRevert as exc:
            if exc.error != "RequestAlreadyPaid":
                return None
            first = exc.values["firstAllocationId"]
        else:  # pragma: no cover - the empty request always reverts
            return None
        logs = self.chain._retry(
            lambda: self.models.events.ModelAllocated().get_logs(
                argument_filters={"allocationId": first}, from_block=0
            ),
            "read the request's allocation",
        )
        if not logs:
            raise ChainError(f"request 0x{rid.hex()} is paid on chain but its logs are not available")
        tx_hash = logs[0]["transactionHash"]
        receipt = self.chain._retry(
            lambda: self.chain.w3.eth.get_transaction_receipt(tx_hash), "read a receipt"
        )
        return self._allocations(receipt, "0x" + rid.hex(), replayed=True)

    def _allocations(self, receipt: Any, request_id: str, replayed: bool) -> list[Allocation]:
        out = []
        for ev in self.models.events.ModelAllocated().process_receipt(receipt, errors=DISCARD):
            a = ev["args"]
            qos = math.inf if is_exact(a["qos"]) else from_fixed(a["qos"])
            out.append(
                Allocation(
                    a["allocationId"],
                    self.model(a["modelId"]),
                    qos,
                    from_fixed(a["distance"]),
                    a["price"],
                    a["requester"],
                    request_id,
                    replayed,
                )
            )
        return out

    def allocation(self, allocation_id: int) -> tuple[str, int, bool]:
        """(requester, model id, reviewed) of an allocation."""
        return tuple(self.chain.call(self.models.functions.getAllocation(allocation_id)))

    # ------------------------------------------------------------ content
    def fetch(self, cid: str) -> bytes:
        """The bytes of ``cid`` from the content store, verified against the CID."""
        return self.store.fetch(cid)

    def fetch_to(self, cid: str, path: str | os.PathLike[str]) -> int:
        """Write the bytes of ``cid``, verified while they stream in, to ``path``; returns the size."""
        return self.store.fetch_to(cid, path)

    # ------------------------------------------------------------ reviews and payments
    def review(self, allocation: int | Allocation, value: float) -> TxResult:
        """Review an allocation (its id or the :class:`Allocation`) with ``value`` in [0, 1].

        Paper: updateModelRep. Only the requester it was allocated to may review it, once.
        """
        allocation_id = allocation.allocation_id if isinstance(allocation, Allocation) else allocation
        if isinstance(allocation_id, bool) or not isinstance(allocation_id, int) or allocation_id < 0:
            raise ValueError(
                f"allocation must be an allocation id (int >= 0) or an Allocation, got {allocation!r}"
            )
        return self._tx(self.models.functions.updateModelRep(allocation_id, to_fixed(value, "review")))

    def owed(self, address: str | None = None) -> int:
        """Wei the account can withdraw (model payments and refunds)."""
        return self.chain.call(self.models.functions.owed(to_checksum_address(address or self.address)))

    def withdraw(self) -> int:
        """Withdraw everything owed to this account; returns the amount in wei."""
        result = self._tx(self.models.functions.withdraw())
        return self.models.events.Withdrawn().process_receipt(result.receipt, errors=DISCARD)[0]["args"][
            "amount"
        ]

    def status(self) -> dict[str, Any]:
        """A summary: chain, contracts, this account's balance, owed amount and reputation."""
        try:
            user = self.user()
        except ChainError as exc:
            raise ChainError(f"cannot read the registry: {exc}") from exc
        return {
            "chain": self.chain.description,
            "chain_id": self.chain.w3.eth.chain_id,
            "block": self.chain.w3.eth.block_number,
            "users_manager": self.deployment.users,
            "models_manager": self.deployment.models,
            "content_store": repr(self.store),
            "account": self.address,
            "balance_wei": self.chain.balance(self.address),
            "owed_wei": self.owed(),
            "registered": user.registered,
            "reputation": user.reputation,
            "models_shared": self.model_count(),
            "allocations": self.chain.call(self.models.functions.allocationCount()),
            "contract_balance_wei": self.chain.balance(self.deployment.models),
        }


def bundle_summary(data: bytes) -> dict[str, Any]:
    """What a requester must know before using a shared policy bundle, read from its validated
    manifest (the weights are never decoded): the observation variant it takes and its
    architecture. {} for bytes that are not a policy bundle (the registry stores any file)."""
    from medc_training.bundle import BundleError, manifest_observation, read_manifest

    try:
        manifest = read_manifest(data)
    except BundleError:
        return {}
    out: dict[str, Any] = {"architecture": manifest["architecture"].get("name", "?")}
    if manifest["application"] == "target_localization":
        out["observation"] = manifest_observation(manifest)
    return out


def _check_app(application: str) -> None:
    if not isinstance(application, str) or not application.strip():
        raise ValueError("application must be a non-empty string, e.g. 'target_localization'")


def _features(features: Features) -> tuple[tuple[str, ...], list[int]]:
    if isinstance(features, Mapping):
        names = tuple(sorted(features))
        values = [features[n] for n in names]
    elif isinstance(features, Sequence) and not isinstance(features, str | bytes):
        names, values = (), list(features)
    else:
        raise ValueError("environment features must be a mapping name -> int or a sequence of ints")
    if len(values) > MAX_FEATURES:
        raise ValueError(f"at most {MAX_FEATURES} environment features, got {len(values)}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= _UINT32:
            raise ValueError(f"environment feature values must be integers in [0, {_UINT32}], got {v!r}")
    return names, [int(v) for v in values]


def _weights(weights: Features) -> tuple[tuple[str, ...], list[int]]:
    if isinstance(weights, Mapping):
        names = tuple(sorted(weights))
        raw = [weights[n] for n in names]
    else:
        names, raw = (), list(weights)
    return names, fixed_weights(raw)
