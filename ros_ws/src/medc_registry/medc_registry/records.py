"""What the registry reads from the chain, as records: users, models, allocations, deployments."""

from __future__ import annotations

from dataclasses import dataclass, field

from medc_training.untrusted import UntrustedJSONError, parse_json

#: Longest model description read as JSON (a shared bundle's is a few hundred characters).
MAX_DESCRIPTION_JSON_CHARS = 64 << 10


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


@dataclass
class Deployment:
    """Where the two contracts live."""

    users: str
    models: str
    gas: dict[str, int] = field(default_factory=dict)


def description_features(description: str) -> tuple[str, ...]:
    """The feature names recorded in a model's description (JSON ``{"features": [...]}``), if any.

    Descriptions are anyone's on-chain text: read with the bounded reader of bundle manifests
    (:func:`medc_training.untrusted.parse_json`), so no description can recurse the parser deep;
    one that is not such JSON names no features.
    """
    if not isinstance(description, str) or not description:
        return ()
    try:
        value = parse_json(description, "a model description", MAX_DESCRIPTION_JSON_CHARS)
    except UntrustedJSONError:
        return ()
    names = value.get("features") if isinstance(value, dict) else None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        return ()
    return tuple(names)
