"""The registry facade: the paper's time sequence over one chain client and one content store.

Typical use (embedded chain and a local content store, one call)::

    from medc_registry import Registry
    reg = Registry.embedded("/tmp/medc-store")          # deploys both contracts
    app = DEFAULT_APPLICATION                            # from medc_training.envs
    alice, bob = reg.as_user(1), reg.as_user(2)
    alice.register_user(); bob.register_user()
    m = alice.share_model(bundle_bytes, app, {"agents": 1, "walls": 3}, price=10**15)
    allocs = bob.request_models(app, {"agents": 3, "walls": 2}, count=2)
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
import os
from collections.abc import Callable, Mapping
from typing import Any

from eth_utils import to_checksum_address
from medc_training.qos import from_fixed, to_fixed
from web3.logs import DISCARD

from .catalog import MAX_DESCRIPTION_BYTES, ModelCatalog, bundle_summary, model_description
from .chain import ChainClient, ChainError, TxResult
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
from .journal import PaidRequests, PendingRequests
from .ranker import Ranker, Ranking
from .records import Allocation, Deployment, SharedModel, UserInfo, format_eth
from .request import (
    MAX_CANDIDATES,
    MAX_COUNT,
    MAX_FEATURES,
    Features,
    ModelRequest,
    check_application,
    parse_features,
    request_id_from,
    takes_request,
)

__all__ = [
    "MAX_CANDIDATES",
    "MAX_COUNT",
    "MAX_DESCRIPTION_BYTES",
    "MAX_FEATURES",
    "Allocation",
    "Deployment",
    "Features",
    "ModelRequest",
    "PendingRequests",
    "Registry",
    "SharedModel",
    "UserInfo",
    "bundle_summary",
    "check_share_text",
    "deploy_contracts",
    "format_eth",
    "model_description",
    "request_id_from",
]


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
    """The MEDC registry for one signing account (see the module docstring).

    A facade: requests are typed (:class:`~medc_registry.request.ModelRequest`), ranked by
    :class:`~medc_registry.ranker.Ranker` and paid exactly once by
    :class:`~medc_registry.journal.PaidRequests`; the shared models are read through
    :class:`~medc_registry.catalog.ModelCatalog`; all over the chain client's public API.
    """

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
        #: The last transaction this registry sent (hash, gasUsed, receipt), e.g. for gas figures.
        self.last_tx: TxResult | None = None
        self.models = chain.contract("ModelsManager", deployment.models)
        self.catalog = ModelCatalog(chain, self.models)

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
        reg = cls(chain, store, settings_deployment(settings, chain), account)
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
        other.catalog = self.catalog  # feature names per application, fixed once set on chain
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
            application: the application's name (``medc_training.envs.APPLICATIONS``).
            env_features: environment features (mapping name -> int, or ints in the app's order).
            price: wei a requester pays each time the model is allocated.
            description: extra text or JSON-able details stored with the model.
            cid_version: 0 (``ipfs add``) or 1 (``ipfs add --cid-version=1``).
        """
        _check_share_args(bundle, application, price, description)
        names, values = parse_features(env_features)
        text = self.catalog.new_description(application, names, bytes(bundle), description)
        cid = self.store.add(bytes(bundle), cid_version)
        self.store.pin(cid)
        result = self._tx(self.models.functions.addModel(application, cid, text, list(values), price))
        event = self.models.events.ModelAdded().process_receipt(result.receipt, errors=DISCARD)[0]
        return self.model(event["args"]["modelId"])

    def model(self, model_id: int) -> SharedModel:
        """Model ``model_id`` (ContractRevert ``UnknownModel`` if there is none)."""
        return self.catalog.model(model_id)

    def model_count(self) -> int:
        """Number of shared models."""
        return self.catalog.count()

    def list_models(self, application: str | None = None) -> list[SharedModel]:
        """All shared models (of ``application`` when given)."""
        return self.catalog.list_models(application)

    def feature_names(self, application: str) -> tuple[str, ...] | None:
        """Feature names of ``application`` (fixed by its first model; () when it named none),
        None when no model of it was shared."""
        return self.catalog.feature_names(application)

    # ------------------------------------------------------------ allocation
    @takes_request
    def rank(self, request: ModelRequest, max_price: int | None = None) -> list[int]:
        """The ids of the best ``count`` eligible models for this account, best first (no transaction).

        The contract ranks: ``allocateModels`` is simulated (eth_call, free) on pages of the
        application's models, each page joined by the best ids so far, so the result is the
        contract's own greedy top ``count`` over all of them, however many there are.
        """
        return Ranker(self.chain, self.models, self.address).rank(request, max_price).model_ids

    @takes_request
    def quote(self, request: ModelRequest, max_price: int | None = None) -> tuple[list[int], int]:
        """Which models a request would get now and their total price in wei (no transaction),
        under ``max_price`` per model or the default limit (:meth:`request_models`)."""
        ranking = Ranker(self.chain, self.models, self.address).rank(request, max_price)
        return ranking.model_ids, ranking.price_wei

    @takes_request
    def request_models(
        self,
        request: ModelRequest,
        payment: int | None = None,
        request_id: str | bytes | None = None,
        max_price: int | None = None,
        max_total: int | None = None,
        same_since: float | None = None,
        on_quote: Callable[[Ranking], None] | None = None,
    ) -> list[Allocation]:
        """Request up to ``count`` models (paper: allocateModels) and pay for them, exactly once;
        returns the allocations best first.

        ``payment`` (wei) defaults to the exact price of what would be allocated (:meth:`quote`);
        an overpayment is credited back. Candidates are priced at most ``max_price`` wei each, or
        the default limit (:mod:`medc_registry.ranker`); ``max_total``, ``on_quote``,
        ``request_id`` and ``same_since``, and how a lost answer is resolved, are as
        :meth:`PaidRequests.pay <medc_registry.journal.PaidRequests.pay>` says.
        """
        payer = PaidRequests(self.chain, self.models, self.address, self.pending, self.model)
        allocations = payer.pay(request, payment, request_id, max_price, max_total=max_total,
                                same_since=same_since, on_quote=on_quote)
        if payer.last_tx is not None:
            self.last_tx = payer.last_tx
        return allocations

    def pending_requests(self) -> list[dict[str, Any]]:
        """This account's paid requests not confirmed yet (resolve one by requesting it again)."""
        return [r for r in self.pending.load().values()
                if r["account"] == self.address and "tx_hash" in r and "done" not in r]

    def allocation(self, allocation_id: int) -> tuple[str, int, bool]:
        """(requester, model id, reviewed) of an allocation."""
        return tuple(self.chain.call(self.models.functions.getAllocation(allocation_id)))

    # ------------------------------------------------------------ content
    def fetch(self, cid: str) -> bytes:
        """The bytes of ``cid`` from the content store, verified against the CID."""
        return self.store.fetch(cid)

    def fetch_to(self, cid: str, path: str | os.PathLike[str], overwrite: bool = True) -> int:
        """Write the bytes of ``cid``, verified while they stream in, to ``path`` atomically (never
        through a link there); returns the size. ``overwrite`` False: a file (or link) already at
        ``path`` is refused, before fetching and again at the write."""
        return self.store.fetch_to(cid, path, overwrite)

    # ------------------------------------------------------------ reviews and payments
    def review(self, allocation: int | Allocation, value: float) -> TxResult:
        """Review an allocation (its id or the :class:`Allocation`) with ``value`` in [0, 1].

        Paper: updateModelRep. Only the requester it was allocated to may review it, once.
        """
        allocation_id = _allocation_id(allocation)
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
            "chain_id": self.chain.chain_id(),
            "block": self.chain.block_number(),
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


def settings_deployment(settings: RegistrySettings, chain: ChainClient) -> Deployment:
    """The contracts of the registry ``settings`` describe, on ``chain``: fresh ones on an embedded
    chain, else the recorded ones, whose Models Manager must be there (RegistryHomeError if not)."""
    if settings.embedded:
        return deploy_contracts(chain)
    deployment = Deployment(settings.users_manager, settings.models_manager)
    if not chain.has_code(deployment.models):
        fix = (f"remove {settings.home / STATE_FILE} and run `medc-registry start` again"
               if settings.home is not None else "check the models_manager address")
        raise RegistryHomeError(
            f"no Models Manager contract at {deployment.models} on {settings.chain}: the chain's "
            f"state was lost or the address is wrong; {fix}"
        )
    return deployment


def check_share_text(application: str, description: str | Mapping[str, Any] | None) -> None:
    """Refuse an application name or a description too long to share (checked before the model
    file is read or anything is sent: a 100 KB description would only run out of gas)."""
    check_application(application)
    if description is None:
        return
    text = description if isinstance(description, str) else json.dumps(description, default=str)
    try:
        size = len(text.encode("utf-8"))
    except UnicodeEncodeError:
        raise ValueError("the description must be valid Unicode text (no lone surrogates)") from None
    if size > MAX_DESCRIPTION_BYTES:
        raise ValueError(f"the description is {size} bytes, over the {MAX_DESCRIPTION_BYTES} byte limit")


def _check_share_args(bundle: bytes, application: str, price: int,
                      description: str | Mapping[str, Any] | None) -> None:
    """:meth:`Registry.share_model`'s argument checks, before anything is stored or sent."""
    if not isinstance(bundle, bytes | bytearray) or not bundle:
        raise ValueError("bundle must be non-empty bytes (the model file's content)")
    check_share_text(application, description)
    if not isinstance(price, int) or price < 0 or price >= 2**128:
        raise ValueError(f"price must be an integer number of wei in [0, 2**128), got {price!r}")


def _allocation_id(allocation: int | Allocation) -> int:
    """The id of the allocation :meth:`Registry.review` is given (its id or the :class:`Allocation`);
    ValueError for anything else."""
    allocation_id = allocation.allocation_id if isinstance(allocation, Allocation) else allocation
    if (isinstance(allocation_id, bool) or not isinstance(allocation_id, int)
            or not 0 <= allocation_id < 2**256):
        raise ValueError(
            f"allocation must be an allocation id (0 to 2**256 - 1) or an Allocation, got {allocation!r}"
        )
    return allocation_id
