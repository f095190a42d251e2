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

import json
import math
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from eth_utils import to_checksum_address
from web3.logs import DISCARD

from .chain import ChainClient, ChainError, ContractRevert, TxResult
from .content import ContentStore, LocalContentStore

ONE = 10**18
MAX_FEATURES = 8
_UINT32 = 2**32 - 1
_QOS_EXACT = 2**256 - 1

Features = Mapping[str, int] | Sequence[int]


def to_fixed(value: float, name: str = "value") -> int:
    """A float in [0, 1] as fixed point (1e18 = 1.0)."""
    v = float(value)
    if not (math.isfinite(v) and 0.0 <= v <= 1.0):
        raise ValueError(f"{name} must be between 0 and 1, got {value!r}")
    return round(v * ONE)


def from_fixed(value: int) -> float:
    """Fixed point (1e18 = 1.0) as a float."""
    return value / ONE


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

    @property
    def model_id(self) -> int:
        return self.model.model_id

    @property
    def cid(self) -> str:
        return self.model.cid

    @property
    def owner(self) -> str:
        return self.model.owner


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
        chain = ChainClient.embedded()
        store = LocalContentStore(store_dir or tempfile.mkdtemp(prefix="medc-store-"))
        return cls(chain, store, deploy_contracts(chain), account)

    @classmethod
    def from_home(cls, home: str | None = None, account: int | str = 0) -> Registry:
        """The registry recorded by ``medc-registry start`` / ``deploy`` in ``home``.

        ``home`` defaults to ``$MEDC_HOME`` or ``./.medc``. Raises ``RuntimeError`` with the command
        to run when no chain is configured there or its node does not answer.
        """
        import argparse

        from .cli import open_registry

        return open_registry(argparse.Namespace(home=home, account=account))

    def as_user(self, account: int | str) -> Registry:
        """The same registry acting as another signing account (index or address)."""
        other = Registry(self.chain, self.store, self.deployment, account)
        other._feature_cache = self._feature_cache  # per application, fixed once set on chain
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
        if not isinstance(count, int) or count < 1:
            raise ValueError(f"count must be a positive integer, got {count!r}")
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
        fn = self.models.functions.allocateModels(*args)
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

    def request_models(
        self,
        application: str,
        requirements: Features,
        weights: Features | None = None,
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
        payment: int | None = None,
    ) -> list[Allocation]:
        """Request up to ``count`` models (paper: allocateModels) and pay for them.

        ``payment`` (wei) defaults to the exact price of what would be allocated (see :meth:`quote`);
        any overpayment is credited back and can be withdrawn. Returns the allocations best first.
        """
        args = self._allocate_args(application, requirements, weights, count, min_model_rep, min_owner_rep)
        if payment is None:
            _, payment = self.quote(application, requirements, weights, count, min_model_rep, min_owner_rep)
        if not isinstance(payment, int) or payment < 0:
            raise ValueError(f"payment must be a non-negative integer number of wei, got {payment!r}")
        result = self._tx(self.models.functions.allocateModels(*args), value=payment)
        out = []
        for ev in self.models.events.ModelAllocated().process_receipt(result.receipt, errors=DISCARD):
            a = ev["args"]
            qos = math.inf if a["qos"] == _QOS_EXACT else from_fixed(a["qos"])
            out.append(
                Allocation(
                    a["allocationId"],
                    self.model(a["modelId"]),
                    qos,
                    from_fixed(a["distance"]),
                    a["price"],
                    a["requester"],
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
        raw = [float(weights[n]) for n in names]
    else:
        names, raw = (), [float(w) for w in weights]
    if not raw or any(not math.isfinite(w) or w < 0 for w in raw):
        raise ValueError(f"weights must be non-negative numbers, got {raw!r}")
    total = sum(raw)
    if total <= 0 or abs(total - 1.0) > 1e-9:
        raise ValueError(f"weights must sum to 1, got {total}")
    fixed = [round(w * ONE) for w in raw]
    fixed[-1] += ONE - sum(fixed)  # absorb rounding so the on-chain sum is exactly 1e18
    if fixed[-1] < 0:
        raise ValueError("weights must sum to 1")
    return names, fixed
