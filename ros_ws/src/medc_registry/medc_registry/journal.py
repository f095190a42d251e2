"""Paid requests, exactly once: the journal of requests sent but not confirmed, and their flow.

A paid request carries an id that the Models Manager records and refuses to pay twice. Before its
transaction is sent, :class:`PendingRequests` durably records the id and the signed transaction,
so a run that lost the node's answer is resolved by the next one (:class:`PaidRequests`) instead
of paying again: the original allocation if it was mined, else the same request sent again, which
the contract can only pay once.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from medc_training.qos import from_fixed, is_exact
from medc_training.untrusted import UntrustedJSONError, parse_json, printable
from web3.logs import DISCARD

from .chain import ChainClient, ChainError, ContractRevert, TxResult
from .files import open_lock, write_atomic
from .ranker import Ranker, Ranking
from .records import Allocation, SharedModel, format_eth
from .request import ModelRequest, request_id_from

#: Most seconds a request waits for another run's request on the same pending file to finish.
LOCK_WAIT = 600.0
#: Seconds a confirmed request's record is kept (see PendingRequests.finish).
DONE_KEEP = 3600.0
#: Largest pending-requests file read (a record is a few KB; a home holds a handful).
MAX_PENDING_CHARS = 16 << 20
_HEX = set("0123456789abcdef")


class PendingRecordsError(RuntimeError):
    """The pending-requests file cannot be read as records; the message says what to do."""


class PendingLockTimeout(RuntimeError):
    """Another run's request on the same pending file did not finish within the wait."""


class LockWaitInterrupted(RuntimeError):
    """Interrupted (Ctrl-C) while waiting for another run's request on the same pending file:
    this run had sent nothing."""


class OverBudget(ChainError):
    """A request whose price is over what the caller allows in total; refused before signing."""


def process_start_time() -> float:
    """When this process started (seconds since the epoch; Linux ``/proc``, else now): the moment
    a command-line run began, before its interpreter loaded, for
    :meth:`PaidRequests.pay`'s ``same_since``."""
    try:
        with open("/proc/self/stat", encoding="ascii") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        with open("/proc/stat", encoding="ascii") as fh:
            boot = next(int(line.split()[1]) for line in fh if line.startswith("btime "))
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return time.time()


def _is_hex(text: Any, digits: int | None = None) -> bool:
    return (isinstance(text, str) and text.startswith("0x") and set(text[2:].lower()) <= _HEX
            and (digits is None or len(text) == 2 + digits))


def _record_problem(key: Any, record: Any) -> str | None:
    """Why ``record`` (under ``key``) is not a pending record, or None when it is one."""
    if not isinstance(key, str) or not isinstance(record, dict):
        return "an entry is not a record (an object under an account:request-id key)"
    if not _is_hex(record.get("request_id"), 64):
        return f"record {printable(key, 140)!r} has no request_id of 0x + 64 hex digits"
    if not isinstance(record.get("account"), str) or not isinstance(record.get("fingerprint"), str):
        return f"record {printable(key, 140)!r} lacks its account or fingerprint"
    if "done" in record:
        if not isinstance(record["done"], int | float) or isinstance(record["done"], bool):
            return f"record {printable(key, 140)!r} has a done time that is not a number"
        return None  # confirmed
    if "tx_hash" not in record:
        return None  # recorded before signing: nothing was sent
    ints_ok = all(isinstance(record.get(k), int) and not isinstance(record.get(k), bool)
                  and record[k] >= 0 for k in ("value", "nonce"))
    if not (_is_hex(record["tx_hash"], 64) and _is_hex(record.get("raw")) and ints_ok
            and isinstance(record.get("args"), list) and len(record["args"]) == 7):
        return (f"record {printable(key, 140)!r} of a sent transaction lacks a valid tx_hash, raw, "
                "nonce, value or args")
    return None


class PendingRequests:
    """Paid requests sent but not yet confirmed: one JSON file (``path``), or memory (``None``).

    A record is written (and fsynced) *first*, under :meth:`lock`, before the request is ranked,
    signed or sent: then with the signed transaction and its hash before it is sent, so a run that
    lost the node's answer, or a second run started while the first was still waiting on a slow
    node, resolves that same request instead of paying again.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None, lock_wait: float = LOCK_WAIT) -> None:
        self.path = Path(path) if path is not None else None
        self.lock_wait = lock_wait
        self._memory: dict[str, dict[str, Any]] = {}
        self._thread_lock = threading.Lock()

    def __repr__(self) -> str:
        return f"PendingRequests({str(self.path) if self.path else 'in memory'})"

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the pending file's lock (one request at a time per file, across processes: an
        advisory ``flock`` on ``<path>.lock``, released by the kernel if the holder dies); waits at
        most :attr:`lock_wait` seconds for another run's request to finish."""
        until = time.monotonic() + self.lock_wait
        if not self._thread_lock.acquire(timeout=self.lock_wait):
            raise PendingLockTimeout(self._busy())
        try:
            if self.path is None:
                yield
                return
            fd = self._acquire(until)
            try:
                yield
            finally:
                os.close(fd)  # releases the flock
        finally:
            self._thread_lock.release()

    def _acquire(self, until: float) -> int:
        """The lock file's descriptor with the flock held, waited for until ``until``; Ctrl-C from
        the lock file's creation to the lock held is LockWaitInterrupted (nothing was sent)."""
        fd = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = open_lock(self.path.with_name(self.path.name + ".lock"))
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    return fd
                except BlockingIOError:
                    if time.monotonic() >= until:
                        raise PendingLockTimeout(self._busy()) from None
                    time.sleep(0.05)
        except KeyboardInterrupt:
            if fd is not None:
                os.close(fd)
            raise LockWaitInterrupted(
                f"interrupted while waiting for another run's request on {self.path} to finish; "
                "this run sent nothing and paid nothing") from None
        except BaseException:
            if fd is not None:
                os.close(fd)
            raise

    def _busy(self) -> str:
        return (f"another request on {self.path or 'this registry'} has been running for over "
                f"{self.lock_wait:g} s; wait for it to finish, then run the same request again "
                "(it resolves the other run's payment instead of paying twice)")

    def load(self) -> dict[str, dict[str, Any]]:
        """All records, keyed ``account:request_id`` (PendingRecordsError for a file that is not
        a valid record file, e.g. edited by hand: it may hold an unconfirmed payment, so it is
        never ignored)."""
        if self.path is None:
            return dict(self._memory)
        if not self.path.is_file():
            return {}
        fix = ("it may record a payment that is not confirmed yet: restore it, or move it aside only "
               "when no request of this home is unconfirmed")
        try:
            with open(self.path, encoding="utf-8") as fh:
                text = fh.read(MAX_PENDING_CHARS + 1)
            records = parse_json(text, str(self.path), MAX_PENDING_CHARS, max_string=MAX_PENDING_CHARS)
        except (OSError, UnicodeDecodeError, UntrustedJSONError) as exc:
            raise PendingRecordsError(f"cannot read {self.path}: {exc}; {fix}") from None
        if not isinstance(records, dict):
            raise PendingRecordsError(
                f"{self.path} must hold a JSON object of records, not {type(records).__name__}; {fix}"
            )
        for key, record in records.items():
            problem = _record_problem(key, record)
            if problem is not None:
                raise PendingRecordsError(f"{self.path}: {problem}; {fix}")
        return records

    def _save(self, records: dict[str, dict[str, Any]]) -> None:
        now = time.time()
        records = {k: r for k, r in records.items() if not now - r.get("done", now) > DONE_KEEP}
        if self.path is None:
            self._memory = records
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(self.path, (json.dumps(records, indent=1, sort_keys=True) + "\n").encode())

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

    def finish(self, record: dict[str, Any]) -> None:
        """Mark a request confirmed: its record keeps only its id, fingerprint and the time, for
        :data:`DONE_KEEP` seconds, so an identical request that waited for the lock meanwhile is
        known to be this one (:meth:`done_since`)."""
        records = self.load()
        records[self._key(record)] = {
            "request_id": record["request_id"],
            "account": record["account"],
            "fingerprint": record["fingerprint"],
            "created": record.get("created", 0),
            "done": time.time(),
        }
        self._save(records)

    def done_since(self, account: str, fingerprint: str, since: float) -> dict[str, Any] | None:
        """``account``'s request with this fingerprint confirmed at or after ``since``, if any."""
        for record in self.load().values():
            if (record["account"] == account and record["fingerprint"] == fingerprint
                    and isinstance(record.get("done"), int | float) and record["done"] >= since):
                return record
        return None

    def find(
        self, account: str, fingerprint: str | None = None, request_id: str | None = None
    ) -> dict[str, Any] | None:
        """``account``'s pending record with that request id, or else for the same request, if any
        (a record of a sent transaction before one recorded only; confirmed ones are not pending)."""
        found = None
        for record in self.load().values():
            if record["account"] != account or "done" in record:
                continue
            if (request_id is not None and record["request_id"] == request_id) or (
                request_id is None and record["fingerprint"] == fingerprint
            ):
                if "tx_hash" in record:
                    return record
                found = found or record
        return found



def _check_budget(payment: int | None, max_total: int | None) -> None:
    """ValueError for a payment or total that is not a whole number of wei; OverBudget for a
    payment over the total."""
    if payment is not None and (isinstance(payment, bool) or not isinstance(payment, int) or payment < 0):
        raise ValueError(f"payment must be a non-negative integer number of wei, got {payment!r}")
    if max_total is not None and (isinstance(max_total, bool) or not isinstance(max_total, int)
                                  or max_total < 0):
        raise ValueError(f"max_total must be a non-negative integer number of wei, got {max_total!r}")
    if payment is not None and max_total is not None and payment > max_total:
        raise OverBudget(f"a payment of {format_eth(payment)} is over the {format_eth(max_total)} "
                         "allowed in total; nothing was signed or sent")

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
        self,
        request: ModelRequest,
        payment: int | None,
        request_id: str | bytes | None,
        max_price: int | None = None,
        *,
        max_total: int | None = None,
        same_since: float | None = None,
        on_quote: Callable[[Ranking], None] | None = None,
    ) -> list[Allocation]:
        """Request ``request``'s models and pay for them, exactly once.

        The request carries an id (``request_id``: ``0x`` + 64 hex digits, other text is hashed;
        default random) the contract refuses to pay twice. Under the pending file's lock, a record
        of it (id, fingerprint) is written first and the signed transaction before sending, so a
        later run with the same arguments or id resolves it: the allocations if it was mined
        (``replayed=True``), else the same request sent again. The same request confirmed by
        another run at or after ``same_since`` (default: when this call began) is this one.
        The quote (:class:`~medc_registry.ranker.Ranker`, under ``max_price``) is shown to
        ``on_quote``; over ``max_total`` wei it is refused (:class:`OverBudget`) before signing.
        """
        _check_budget(payment, max_total)
        fingerprint = hashlib.sha256(
            json.dumps([self.account, request.args(), payment, max_price], sort_keys=True).encode()
        ).hexdigest()
        rid = request_id_from(request_id) if request_id is not None else None
        started = time.time() if same_since is None else same_since
        with self.pending.lock():
            record = self.pending.find(self.account, fingerprint, "0x" + rid.hex() if rid else None)
            if record is not None and "tx_hash" in record:
                return self._resolve(record)
            if record is not None:  # an earlier run stopped before signing: nothing was sent
                rid = bytes.fromhex(record["request_id"][2:])
            elif rid is None:
                # The same request finished by another run while this one waited for the lock
                # (started together, or while it waited on a slow node) is this request.
                done = self.pending.done_since(self.account, fingerprint, started)
                if done is not None:
                    paid = self.paid(bytes.fromhex(done["request_id"][2:]))
                    if paid is not None:
                        return paid
            rid = rid or request_id_from(None)
            record = {
                "request_id": "0x" + rid.hex(),
                "account": self.account,
                "fingerprint": fingerprint,
                "created": time.time(),
            }
            self.pending.put(record)  # first of all: a second run sees this request
            try:
                paid = self.paid(rid)
                if paid is not None:
                    self.pending.drop(record)
                    return paid
                fn, args, payment, signed = self._quote_and_sign(rid, request, payment, max_price,
                                                                 max_total, on_quote)
            except BaseException:
                self.pending.drop(record)  # nothing was signed, so nothing can have been sent
                raise
            record = {
                **record,
                "args": args,
                "value": payment,
                "tx_hash": signed.tx_hash,
                "raw": "0x" + signed.raw.hex(),
                "nonce": signed.nonce,
            }
            self.pending.put(record)  # before sending: a lost answer is resolved by the next call
            return self._send(record, fn, signed.raw)

    def _quote_and_sign(self, rid: bytes, request: ModelRequest, payment: int | None,
                        max_price: int | None, max_total: int | None,
                        on_quote: Callable[[Ranking], None] | None) -> tuple:
        """(function, its arguments, payment, signed transaction) of request ``rid``: the request
        quoted (OverBudget over ``max_total``), shown to ``on_quote``, then signed, not sent."""
        ranking = Ranker(self.chain, self.models, self.account).rank(request, max_price)
        if max_total is not None and ranking.price_wei > max_total:
            raise OverBudget(
                f"the {len(ranking.model_ids)} best model(s) under the limit cost "
                f"{format_eth(ranking.price_wei)} together, over the {format_eth(max_total)} "
                "allowed in total; nothing was signed or sent")
        if on_quote is not None:
            on_quote(ranking)
        if payment is None:
            payment = ranking.price_wei
        args = [*request.args(), ranking.positions]
        fn = self.models.functions.allocateModels(rid, *args)
        return fn, args, payment, self.chain.sign(fn, self.account, payment)

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
        self.pending.finish(record)
        return self._allocations(result.receipt, record["request_id"], replayed=False)

    def _settled(self, record: dict[str, Any], exc: ContractRevert) -> list[Allocation]:
        """A request's transaction reverted: the earlier payment if that was why, else the revert."""
        self.pending.drop(record)
        if exc.error == "RequestAlreadyPaid":
            paid = self.paid(bytes.fromhex(record["request_id"][2:]))
            if paid is not None:
                self.pending.finish(record)
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
            self.pending.finish(record)
            return self._allocations(state.receipt, record["request_id"], replayed=True)
        paid = self.paid(rid)
        if paid is not None:
            self.pending.finish(record)
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
