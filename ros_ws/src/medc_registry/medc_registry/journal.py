"""Paid requests, exactly once: the journal of requests sent but not confirmed, and their flow.

A paid request carries an id that the Models Manager records and refuses to pay twice. Before its
transaction is sent, :class:`PendingRequests` durably records the id and the signed transaction,
so a run that lost the node's answer is resolved by the next one (:class:`PaidRequests`) instead
of paying again: the original allocation if it was mined, else the same request sent again, which
the contract can only pay once.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from medc_training.qos import from_fixed, is_exact
from web3.logs import DISCARD

from .chain import ChainClient, ChainError, ContractRevert, TxResult
from .ranker import Ranker
from .records import Allocation, SharedModel
from .request import ModelRequest, request_id_from


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


class PaidRequests:
    """Pays requests of ``account`` to ``models`` (a ModelsManager contract) at most once each.

    ``model_of(model_id)`` reads a :class:`SharedModel` for the allocations; :attr:`last_tx` is the
    transaction the last :meth:`pay` sent, None when it sent none (a replayed request).
    """

    def __init__(
        self,
        chain: ChainClient,
        models: Any,
        account: str,
        pending: PendingRequests,
        model_of: Callable[[int], SharedModel],
    ) -> None:
        self.chain = chain
        self.models = models
        self.account = account
        self.pending = pending
        self.model_of = model_of
        self.last_tx: TxResult | None = None

    def pay(
        self, request: ModelRequest, payment: int | None, request_id: str | bytes | None
    ) -> list[Allocation]:
        """Request ``request``'s models and pay for them, exactly once (see Registry.request_models)."""
        if payment is not None and (isinstance(payment, bool) or not isinstance(payment, int) or payment < 0):
            raise ValueError(f"payment must be a non-negative integer number of wei, got {payment!r}")
        fingerprint = hashlib.sha256(
            json.dumps([self.account, request.args(), payment], sort_keys=True).encode()
        ).hexdigest()
        rid = request_id_from(request_id) if request_id is not None else None
        record = self.pending.find(self.account, fingerprint, "0x" + rid.hex() if rid else None)
        if record is not None:
            return self._resolve(record)
        rid = rid or request_id_from(None)
        paid = self.paid(rid)
        if paid is not None:
            return paid
        ranking = Ranker(self.chain, self.models, self.account).rank(request)
        if payment is None:
            payment = ranking.price_wei
        args = [*request.args(), ranking.positions]
        fn = self.models.functions.allocateModels(rid, *args)
        signed = self.chain.sign(fn, self.account, payment)
        record = {
            "request_id": "0x" + rid.hex(),
            "account": self.account,
            "fingerprint": fingerprint,
            "args": args,
            "value": payment,
            "tx_hash": signed.tx_hash,
            "raw": "0x" + signed.raw.hex(),
            "nonce": signed.nonce,
            "created": time.time(),
        }
        self.pending.put(record)  # before sending: a lost answer is resolved by the next call
        return self._send(record, fn, signed.raw)

    def paid(self, rid: bytes) -> list[Allocation] | None:
        """The allocations of request ``rid`` if this account already paid it, else None.

        The contract's request record (``paidRequest``) names the first allocation and the block
        of the paying transaction, whose receipt holds the allocations.
        """
        paid, first, block = self.chain.call(self.models.functions.paidRequest(self.account, rid))
        if not paid:
            return None
        logs = self.chain.logs(self.models.events.ModelAllocated, block, block, allocationId=first)
        if not logs:
            raise ChainError(f"request 0x{rid.hex()} is paid on chain but its logs are not available")
        receipt = self.chain.receipt(logs[0]["transactionHash"])
        return self._allocations(receipt, "0x" + rid.hex(), replayed=True)

    def _send(self, record: dict[str, Any], fn: Any, raw: bytes) -> list[Allocation]:
        try:
            result = self.chain.send_raw(raw, fn=fn, sender=self.account, value=record["value"])
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
            paid = self.paid(bytes.fromhex(record["request_id"][2:]))
            if paid is not None:
                return paid
        raise exc

    def _resolve(self, record: dict[str, Any]) -> list[Allocation]:
        """Finish a request recorded by an earlier call whose outcome was not seen."""
        rid = bytes.fromhex(record["request_id"][2:])
        fn = self.models.functions.allocateModels(rid, *record["args"])
        try:
            state = self.chain.lookup(record["tx_hash"], fn, self.account, record["value"])
        except ContractRevert as exc:
            return self._settled(record, exc)
        if isinstance(state, TxResult):
            self.pending.drop(record)
            return self._allocations(state.receipt, record["request_id"], replayed=True)
        paid = self.paid(rid)
        if paid is not None:
            self.pending.drop(record)
            return paid
        raw = bytes.fromhex(record["raw"][2:])
        if state == "unknown" and record["nonce"] < self.chain.pending_nonce(self.account):
            # The nonce went to another transaction, so the recorded one can never be mined:
            # sign the same request (same id) again; the contract still pays it at most once.
            signed = self.chain.sign(fn, self.account, record["value"])
            record = {
                **record,
                "tx_hash": signed.tx_hash,
                "raw": "0x" + signed.raw.hex(),
                "nonce": signed.nonce,
            }
            self.pending.put(record)
            raw = signed.raw
        return self._send(record, fn, raw)

    def _allocations(self, receipt: Any, request_id: str, replayed: bool) -> list[Allocation]:
        out = []
        for ev in self.models.events.ModelAllocated().process_receipt(receipt, errors=DISCARD):
            a = ev["args"]
            qos = math.inf if is_exact(a["qos"]) else from_fixed(a["qos"])
            out.append(
                Allocation(
                    a["allocationId"],
                    self.model_of(a["modelId"]),
                    qos,
                    from_fixed(a["distance"]),
                    a["price"],
                    a["requester"],
                    request_id,
                    replayed,
                )
            )
        return out
