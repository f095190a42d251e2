"""The contract's own ranking over all of an application's models, page by page, for free,
under a price limit, with equal QoS going to the cheaper model.

``allocateModels`` ranks at most :data:`~medc_registry.request.MAX_CANDIDATES` candidates (positions
in the application's Models List) per call. :class:`Ranker` simulates it (eth_call, nothing is
sent) on pages of the Models List, each page joined by the best so far, so the result is the
contract's greedy top ``count`` over every model, however many were shared.

Money: only models priced at most a limit per model are candidates. Without one given, the limit
is :data:`DEFAULT_PRICE_FACTOR` times the cheapest non-zero price among the models the request
could get (:meth:`Ranker.default_limit`), never more than the account holds: a seller can only
lower that reference by pricing low, never raise it, so no model priced far above the market is
paid for unless the caller names a limit that covers it. Ties: the contract breaks equal QoS by
the lower model id; the ranker then replaces, at the boundary of the top ``count``, a model by
an equally ranked cheaper one (then by the lower id), and the paying call names exactly the
models chosen, so equal QoS never costs more than the cheapest of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from medc_training.qos import distance, rank_key

from .chain import ChainClient, ChainError, ContractRevert
from .records import format_eth
from .request import MAX_CANDIDATES, ModelRequest, request_id_from

#: The default price limit per model: this many times the cheapest non-zero price among the
#: models a request could get (see the module docstring).
DEFAULT_PRICE_FACTOR = 10


@dataclass(frozen=True)
class PriceLimit:
    """The most one model of a request may cost, and where that figure comes from."""

    #: Wei; models dearer than this are not candidates.
    wei: int
    #: True when the caller named it; False for the default rule.
    given: bool
    #: The default rule's reference: the cheapest non-zero price among the models the request could
    #: get (None when it was given, or every such model is free).
    reference_wei: int | None = None
    #: The account's balance, when it capped the default below the rule's figure.
    balance_cap_wei: int | None = None
    #: Models of the application priced above the limit (never candidates).
    passed_over: int = 0

    def describe(self) -> str:
        """One line: the limit and its rule, e.g. for the CLI before it pays."""
        if self.given:
            text = f"at most {format_eth(self.wei)} per model (given)"
        elif self.reference_wei is None:
            text = "free models only (every model this request could get at a price is free)"
        else:
            text = (f"at most {format_eth(self.wei)} per model: {DEFAULT_PRICE_FACTOR} x the cheapest "
                    f"non-zero price the request could get, {format_eth(self.reference_wei)}")
            if self.balance_cap_wei is not None:
                text += f", capped at the account's balance {format_eth(self.balance_cap_wei)}"
        if self.passed_over:
            text += f"; {self.passed_over} dearer model(s) passed over"
            if not self.given:
                text += " (name a higher limit to consider them)"
        return text


@dataclass(frozen=True)
class Ranking:
    """The best models of a request now: ids best first, their Models List positions, their price,
    and the price limit they were chosen under."""

    model_ids: list[int]
    positions: list[int]
    price_wei: int
    limit: PriceLimit | None = None


class Ranker:
    """Ranks requests of ``sender`` with simulated calls of ``models`` (a ModelsManager contract)."""

    def __init__(self, chain: ChainClient, models: Any, sender: str) -> None:
        self.chain = chain
        self.models = models
        self.sender = sender
        self._users: Any = None

    def models_list(self, application: str) -> list[int]:
        """The application's Models List: its model ids in the order shared, from the contract's
        ``ApplicationAdded`` and ``ModelAdded`` events (the Models Manager has no view of it: one
        more external function would take its deployment over the paper's Table III)."""
        return models_list(self.chain, self.models, application)

    def rank(self, request: ModelRequest, max_price: int | None = None) -> Ranking:
        """The best ``request.count`` models over the whole Models List under a price limit, equal
        QoS going to the cheaper model, and their price.

        Only models priced at most ``max_price`` wei each are candidates; without ``max_price``,
        at most :meth:`default_limit` (never the account's balance: one exact match priced at
        1,000 ETH beside honest ones at 0.001 ETH is passed over). Prices come from the
        ``ModelAdded`` events (a model's price never changes), so this costs no extra call per
        model. ContractRevert ``NoEligibleModels`` (its values name the limit) when no model under
        the limit is eligible.
        """
        if max_price is not None and (isinstance(max_price, bool) or not isinstance(max_price, int)
                                      or max_price < 0):
            raise ValueError(f"max_price must be a non-negative integer number of wei, got {max_price!r}")
        listed = models_with_prices(self.chain, self.models, request.application)
        balance = self.chain.balance(self.sender)
        if max_price is None:
            limit = self.default_limit(request, listed, balance)
        else:
            limit = PriceLimit(max_price, True, passed_over=sum(1 for _, p in listed if p > max_price))
        price_of = dict(listed)
        position = {model_id: pos for pos, (model_id, _price) in enumerate(listed)}
        allowed = [pos for pos, (_id, price) in enumerate(listed) if price <= limit.wei]
        refusal = {"max_price_wei": limit.wei, "limit": limit.describe()}
        best = self._best(request, allowed, position, balance) if allowed else []
        if not best:
            raise ContractRevert("NoEligibleModels", refusal)
        best = self._cheaper_ties(request, best, allowed, position, price_of, balance)
        positions = sorted(position[i] for i in best)
        ids, price = self.simulate(request, positions, balance)
        return Ranking(ids, positions, price, limit)

    def default_limit(self, request: ModelRequest, listed: list[tuple[int, int]], balance: int) -> PriceLimit:
        """The limit per model when none is given: :data:`DEFAULT_PRICE_FACTOR` times the cheapest
        non-zero price among the models this request could get (those the contract would rank:
        reputations at the minimums, not the sender's own), capped at the account's balance; 0
        (free models only) when every such model is free. Found by simulated calls over price
        levels (a binary search), so it costs a few calls however many models there are."""
        levels = sorted({p for _id, p in listed if 0 < p <= balance})
        position = {model_id: pos for pos, (model_id, _price) in enumerate(listed)}

        def any_eligible(level: int) -> bool:
            allowed = [position[i] for i, p in listed if 0 < p <= level]
            return bool(self._best(request, allowed, position, balance, count=1, first=True))

        reference = None
        if levels and any_eligible(levels[-1]):
            lo, hi = 0, len(levels) - 1  # levels[hi] has an eligible model
            while lo < hi:
                mid = (lo + hi) // 2
                if any_eligible(levels[mid]):
                    hi = mid
                else:
                    lo = mid + 1
            reference = levels[hi]
        wei = 0 if reference is None else DEFAULT_PRICE_FACTOR * reference
        cap = balance if wei > balance else None
        wei = min(wei, balance)
        return PriceLimit(wei, False, reference, cap, sum(1 for _, p in listed if p > wei))

    def _best(self, request: ModelRequest, allowed: list[int], position: dict[int, int], balance: int,
              count: int | None = None, first: bool = False) -> list[int]:
        """The contract's top ``count`` (default: the request's) among ``allowed`` positions, page
        by page; [] when none is eligible. ``first``: stop at the first page with a result."""
        count = request.count if count is None else count
        if count != request.count:
            request = ModelRequest(request.application, request.requirements, request.weights, count,
                                   request.min_model_rep, request.min_owner_rep)
        page = MAX_CANDIDATES - request.count
        best: list[int] = []
        for start in range(0, len(allowed), page):
            try:
                best, _price = self.simulate(
                    request, sorted({position[i] for i in best} | set(allowed[start:start + page])),
                    balance)
            except ContractRevert as exc:
                if exc.error != "NoEligibleModels":
                    raise
            if first and best:
                break
        return best

    def _cheaper_ties(self, request: ModelRequest, best: list[int], allowed: list[int],
                      position: dict[int, int], price_of: dict[int, int], balance: int) -> list[int]:
        """``best`` (the contract's top ``count``, equal QoS by the lower id) with equal QoS going to
        the cheaper model instead: at the boundary of the top ``count``, a model is replaced by an
        equally ranked cheaper one found among the rest (ranking keys from the contract's rules
        as ``medc_training.qos`` states them; ``test_qos_mirror`` holds them equal)."""
        if len(best) < request.count:
            return best  # every eligible model under the limit is in
        dearest = max(price_of[i] for i in best)
        taken = {position[i] for i in best}
        price_at = {pos: price_of[i] for i, pos in position.items()}
        cheaper = [pos for pos in allowed if pos not in taken and price_at[pos] < dearest]
        if not cheaper:
            return best
        keys = self._keys(request, best)
        boundary = min(keys.values())
        ties: list[int] = []
        while cheaper:
            found = self._best(request, cheaper, position, balance)
            if not found:
                break
            keys.update(self._keys(request, found))
            tied = [i for i in found if keys[i] == boundary]
            ties += tied
            if len(tied) < len(found):
                break  # the rest rank below the boundary
            done = {position[i] for i in found}
            cheaper = [pos for pos in cheaper if pos not in done]
        if not ties:
            return best
        above = [i for i in best if keys[i] > boundary]
        group = sorted([i for i in best if keys[i] == boundary] + ties, key=lambda i: (price_of[i], i))
        return above + group[:request.count - len(above)]

    def _keys(self, request: ModelRequest, model_ids: list[int]) -> dict[int, int]:
        """Each model's ranking key for ``request`` (the contract's, by its rules)."""
        if self._users is None:
            users_address = self.chain.call(self.models.functions.users())
            self._users = self.chain.contract("UsersManager", users_address)
        out = {}
        owner_rep: dict[str, int] = {}
        for model_id in model_ids:
            owner, _app, env, _price, model_rep, _count, _total = self.chain.call(
                self.models.functions.getModel(model_id))
            if owner not in owner_rep:
                owner_rep[owner] = self.chain.call(self._users.functions.reputationOf(owner))
            try:
                dist = distance(list(env), list(request.requirements), list(request.weights) or None)
            except ValueError as exc:
                raise ChainError(f"model {model_id} does not match the request's features: {exc}") from None
            out[model_id] = rank_key(dist, owner_rep[owner], model_rep)
        return out

    def simulate(
        self, request: ModelRequest, positions: list[int], balance: int | None = None
    ) -> tuple[list[int], int]:
        """Model ids ``allocateModels`` would allocate from these positions of the application's
        Models List now, best first, and their price (an eth_call: nothing is sent). ``balance``:
        the sender's, to refuse clearly a total it cannot pay."""
        fn = self.models.functions.allocateModels(request_id_from(None), *request.args(), sorted(positions))
        try:
            ids, _ = self.chain.call(fn, sender=self.sender, value=0)
            return list(ids), 0
        except ContractRevert as exc:
            if exc.error != "InsufficientPayment":
                raise
            # The revert names the exact price of what would be allocated.
            required = exc.values["required"]
        if balance is not None and required > balance:
            raise ChainError(
                f"the {request.count} best model(s) cost {required} wei together, more than the "
                f"account's balance of {balance} wei: fund the account, lower the count or set a "
                "maximum price per model"
            )
        ids, _ = self.chain.call(fn, sender=self.sender, value=required)
        return list(ids), required


def models_with_prices(chain: ChainClient, models: Any, application: str) -> list[tuple[int, int]]:
    """``application``'s Models List on ``models`` (a ModelsManager contract) with each model's
    price in wei, in the order shared, from the ``ModelAdded`` events; ContractRevert
    ``UnknownApplication`` when no model of it was shared."""
    added = chain.logs(models.events.ApplicationAdded, 0)
    app_ids = [log["args"]["appId"] for log in added if log["args"]["application"] == application]
    if not app_ids:
        raise ContractRevert("UnknownApplication", {"application": application})
    logs = chain.logs(models.events.ModelAdded, 0, appId=app_ids[0])
    return sorted((log["args"]["modelId"], log["args"]["price"]) for log in logs)


def models_list(chain: ChainClient, models: Any, application: str) -> list[int]:
    """``application``'s Models List on ``models`` (a ModelsManager contract): its model ids in the
    order shared; ContractRevert ``UnknownApplication`` when no model of it was shared."""
    return [model_id for model_id, _price in models_with_prices(chain, models, application)]
