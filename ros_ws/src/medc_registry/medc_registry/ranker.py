"""The contract's own ranking over all of an application's models, page by page, for free.

``allocateModels`` ranks at most :data:`~medc_registry.request.MAX_CANDIDATES` candidates (positions
in the application's Models List) per call. :class:`Ranker` simulates it (eth_call, nothing is
sent) on pages of the Models List, each page joined by the best so far, so the result is the
contract's greedy top ``count`` over every model, however many were shared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .chain import ChainClient, ChainError, ContractRevert
from .request import MAX_CANDIDATES, ModelRequest, request_id_from


@dataclass(frozen=True)
class Ranking:
    """The best models of a request now: ids best first, their Models List positions, their price."""

    model_ids: list[int]
    positions: list[int]
    price_wei: int


class Ranker:
    """Ranks requests of ``sender`` with simulated calls of ``models`` (a ModelsManager contract)."""

    def __init__(self, chain: ChainClient, models: Any, sender: str) -> None:
        self.chain = chain
        self.models = models
        self.sender = sender

    def models_list(self, application: str) -> list[int]:
        """The application's Models List: its model ids in the order shared, from the contract's
        ``ApplicationAdded`` and ``ModelAdded`` events (the Models Manager has no view of it: one
        more external function would take its deployment over the paper's Table III)."""
        return models_list(self.chain, self.models, application)

    def rank(self, request: ModelRequest, max_price: int | None = None) -> Ranking:
        """The contract's best ``request.count`` models over the whole Models List, and their price.

        Only models priced at most ``max_price`` wei each are candidates; without ``max_price``,
        at most the sender's balance (a model it could never pay for cannot block the ranking:
        one model priced at 2**128 - 1 wei that matches exactly is simply passed over). Prices
        come from the ``ModelAdded`` events (a model's price never changes), so this costs no
        extra call per model.
        """
        if max_price is not None and (isinstance(max_price, bool) or not isinstance(max_price, int)
                                      or max_price < 0):
            raise ValueError(f"max_price must be a non-negative integer number of wei, got {max_price!r}")
        listed = models_with_prices(self.chain, self.models, request.application)
        balance = self.chain.balance(self.sender)
        limit = balance if max_price is None else max_price
        position = {model_id: pos for pos, (model_id, _price) in enumerate(listed)}
        allowed = [pos for pos, (_id, price) in enumerate(listed) if price <= limit]
        if not allowed:
            raise ContractRevert("NoEligibleModels", {"max_price_wei": limit} | (
                {} if max_price is not None else {"balance_wei": balance}))
        page = MAX_CANDIDATES - request.count
        best: list[int] = []
        price = 0
        for start in range(0, len(allowed), page):
            try:
                best, price = self.simulate(
                    request, [position[i] for i in best] + allowed[start:start + page], balance
                )
            except ContractRevert as exc:
                if exc.error != "NoEligibleModels":
                    raise
        if not best:
            raise ContractRevert("NoEligibleModels")
        return Ranking(best, sorted(position[i] for i in best), price)

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
