"""One chain client for the registry contracts: embedded eth-tester or any JSON-RPC node.

* :meth:`ChainClient.embedded` runs py-evm in process (eth-tester); nothing persists.
* :meth:`ChainClient.connect` talks to a JSON-RPC URL (anvil, Besu, Quorum, geth) and signs
  locally with the given private keys; ``poa=True`` adds web3's ``ExtraDataToPOAMiddleware`` for
  clique/IBFT/QBFT consortium chains whose blocks carry long ``extraData``.

Every transaction is signed once; :meth:`ChainClient.transact` re-sends the *same* signed bytes
when the node times out or restarts and then looks the receipt up by hash, so a retry can never
pay twice (the nonce is fixed). Reverts with the contracts' custom errors become
:class:`ContractRevert` with the error's name, its arguments and a readable message.

Every chain call (a read, a contract call, or one transaction from signing to its receipt) has
one total deadline, the client's :class:`RetryPolicy`'s ``deadline`` seconds (default
:data:`DEFAULT_DEADLINE`), retries included: each HTTP request's timeout is cut to what is left of
it, and web3's own HTTP retries are switched off so they never nest inside the client's. The client
owns its retry policy and its :class:`TxSender` (signed bytes to a receipt), each built from what
it needs and tested without a chain.
"""

from __future__ import annotations

import ast
import contextlib
import http.client
import json
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from eth_abi import decode as abi_decode
from eth_account import Account
from eth_utils import keccak, to_checksum_address
from medc_training.untrusted import json_depth, printable
from web3 import Web3
from web3.exceptions import TimeExhausted, TransactionNotFound

from .compile import load_artifact

#: Total seconds one chain call may take, retries and receipt waiting included.
DEFAULT_DEADLINE = 60.0

#: Contracts whose ABIs (and custom errors) the client knows.
CONTRACT_NAMES = ("UsersManager", "ModelsManager", "ReentrantWithdrawer")

#: Readable explanations of the contracts' custom errors.
ERROR_HINTS = {
    "AlreadyRegistered": "this account is already registered",
    "UnregisteredUser": "the account is not registered: run register first",
    "NotAdmin": "only the deployer may do this",
    "NotManager": "only the Models Manager contract may update user records",
    "ManagerAlreadySet": "the Users Manager is already bound to a Models Manager",
    "ZeroAddress": "the zero address is not allowed",
    "ZeroCount": "the number of models must be positive",
    "ReviewOutOfRange": "a review must be between 0 and 1",
    "ReviewsExceedAllocations": "more reviews than allocations",
    "UnknownModel": "no model with that id",
    "UnknownApplication": "no model has been shared for that application",
    "UnknownAllocation": "no allocation with that id",
    "EmptyApplication": "the application name is empty",
    "InvalidCid": "the CID is empty or too long",
    "TooManyFeatures": "too many environment features",
    "FeatureCountMismatch": "the number of environment features differs from the application's",
    "InvalidWeights": "weights must be one per feature and sum to 1",
    "PriceTooLarge": "the price does not fit in 128 bits",
    "InvalidCount": "the number of models requested must be positive",
    "NoEligibleModels": "no model meets the requirements (application, reputations, not your own)",
    "InsufficientPayment": "the payment is less than the price of the allocated models",
    "NotAllocatedRequester": "only the requester the model was allocated to may review it",
    "AlreadyReviewed": "this allocation has already been reviewed",
    "NothingToWithdraw": "nothing is owed to this account",
    "TransferFailed": "the payout transfer was rejected by the receiver",
    "RequestAlreadyPaid": "this request id was already paid and allocated; nothing was paid again",
    "TooManyCandidates": "pass 1 to 256 candidates, positions in the application's Models List "
    "(Registry.request_models ranks larger applications page by page)",
    "InvalidCandidate": "candidates must be strictly increasing positions in the application's Models List",
    "MalformedRevert": "the call reverted, but the node's revert data is truncated or malformed",
}


#: Node answers meaning an earlier attempt of the same signed transaction got through.
_ALREADY_SENT = ("already known", "known transaction", "nonce too low", "already imported")


class ChainError(RuntimeError):
    """The chain could not be reached or a transaction did not go through."""


class ContractRevert(ChainError):
    """A contract call reverted; ``error`` is the custom error's name, ``values`` its arguments."""

    def __init__(self, error: str, values: dict[str, Any] | None = None, raw: str = "") -> None:
        self.error = error
        self.values = values or {}
        self.raw = raw
        hint = ERROR_HINTS.get(error, "")
        args = ", ".join(f"{k}={v}" for k, v in self.values.items())
        super().__init__(f"{error}({args})" + (f": {hint}" if hint else ""))


@dataclass(frozen=True)
class TxResult:
    """A mined, successful transaction."""

    tx_hash: str
    gas_used: int
    block_number: int
    receipt: Any
    contract_address: str | None = None


def _error_table() -> dict[bytes, tuple[str, list[str], list[str]]]:
    table: dict[bytes, tuple[str, list[str], list[str]]] = {}
    for name in CONTRACT_NAMES:
        for item in load_artifact(name)["abi"]:
            if item.get("type") != "error":
                continue
            types = [i["type"] for i in item["inputs"]]
            selector = keccak(text=f"{item['name']}({','.join(types)})")[:4]
            table[selector] = (item["name"], [i["name"] for i in item["inputs"]], types)
    return table


_ERRORS: dict[bytes, tuple[str, list[str], list[str]]] | None = None


def _revert_bytes(exc: BaseException) -> bytes | None:
    """Revert data carried by a web3 / eth-tester exception, if any."""
    data = getattr(exc, "data", None)
    if isinstance(data, dict):
        data = data.get("data")
    if isinstance(data, str) and data.startswith("0x"):
        try:
            return bytes.fromhex(data[2:])
        except ValueError:
            return b"\xff" + data[2:].encode("ascii", "replace")[:1024]  # malformed: decodes as "Reverted"
    if isinstance(data, bytes | bytearray):
        return bytes(data)
    for arg in getattr(exc, "args", ()):
        if isinstance(arg, bytes | bytearray):
            return bytes(arg)
        if isinstance(arg, str):
            # eth-tester: "execution reverted: b'...'" ; JSON-RPC nodes: "...: 0x..."
            for marker in ("b'", 'b"'):
                idx = arg.find(marker)
                if idx >= 0:
                    try:
                        value = ast.literal_eval(arg[idx:])
                    except (ValueError, SyntaxError):
                        continue
                    if isinstance(value, bytes):
                        return value
            idx = arg.rfind("0x")
            if idx >= 0:
                hexpart = arg[idx + 2 :].split()[0].strip("'\",")
                try:
                    return bytes.fromhex(hexpart)
                except ValueError:
                    pass
    return None


def decode_revert(exc: BaseException) -> ContractRevert | None:
    """The :class:`ContractRevert` for a reverted call's exception, or None if it is not a revert."""
    global _ERRORS
    if _ERRORS is None:
        _ERRORS = _error_table()
    data = _revert_bytes(exc)
    if data is None:
        text = str(exc)
        if "revert" in text.lower():
            return ContractRevert("Reverted", {"reason": text})
        return None
    return decode_error_data(data)


def decode_error_data(data: bytes) -> ContractRevert:
    """The :class:`ContractRevert` for raw revert data (custom error, Error(string) or Panic)."""
    global _ERRORS
    if _ERRORS is None:
        _ERRORS = _error_table()
    try:
        if len(data) >= 4 and data[:4] in _ERRORS:
            name, names, types = _ERRORS[data[:4]]
            values = abi_decode(types, data[4:]) if types else ()
            values = [
                to_checksum_address(v) if t == "address" else "0x" + v.hex() if isinstance(v, bytes) else v
                for t, v in zip(types, values)
            ]
            return ContractRevert(name, dict(zip(names, values)), "0x" + data.hex())
        if data[:4] == bytes.fromhex("08c379a0"):  # Error(string)
            reason = printable(abi_decode(["string"], data[4:])[0], 500)
            return ContractRevert("Error", {"reason": reason}, "0x" + data.hex())
        if data[:4] == bytes.fromhex("4e487b71"):  # Panic(uint256)
            return ContractRevert("Panic", {"code": abi_decode(["uint256"], data[4:])[0]}, "0x" + data.hex())
    except Exception:  # eth_abi's InsufficientDataBytes, NonEmptyPaddingBytes, ...: truncated data
        return ContractRevert("MalformedRevert", {"data": "0x" + data[:68].hex()}, "0x" + data.hex())
    return ContractRevert("Reverted", {"data": "0x" + data[:68].hex()}, "0x" + data.hex())


def _refusal(exc: BaseException, what: str) -> ChainError:
    """The typed error for a node's answer that is neither a result nor a transient failure: the
    :class:`ContractRevert` of a revert, :class:`MalformedAnswer` for a result that does not decode
    (e.g. a short ``eth_call`` answer), else a :class:`ChainError` naming the node's reason."""
    from eth_abi.exceptions import DecodingError
    from web3.exceptions import BadFunctionCallOutput

    revert = decode_revert(exc)
    if revert is not None:
        return revert
    if isinstance(exc, BadFunctionCallOutput | DecodingError):
        return MalformedAnswer(f"the node's answer to {what} does not decode as its result "
                               f"({type(exc).__name__}: {printable(str(exc), 300)})")
    return ChainError(f"the node refused {what} ({type(exc).__name__}): {printable(str(exc), 500)}")


def _is_transient(exc: BaseException) -> bool:
    """Connection-level failures worth a retry (node restarting, timeouts)."""
    import requests

    transient = (ConnectionError, TimeoutError, OSError, requests.exceptions.RequestException, TimeExhausted)
    return isinstance(exc, transient)


@dataclass(frozen=True)
class SignedTx:
    """A signed transaction not sent yet: its bytes, hash and nonce."""

    raw: bytes
    tx_hash: str
    nonce: int
    sender: str
    value: int


#: Largest JSON-RPC answer read (a page of logs or a block is far smaller); refused past it.
MAX_RPC_ANSWER_BYTES = 32 << 20
#: Deepest nesting of a JSON-RPC answer parsed (web3's answers nest 5 levels or so).
MAX_RPC_ANSWER_DEPTH = 64


class MalformedAnswer(ChainError):
    """The node's answer is too large, not JSON, or not what the call returns; never retried."""


def _deadline_provider(url: str, timeout: float, retry: RetryPolicy) -> Any:
    """An HTTPProvider without web3's retries whose every request, headers and body included,
    ends within what is left of the ``retry`` policy's current call (or ``timeout``), and whose
    answers are size-capped and depth-checked before parsing (:mod:`medc_registry.bounded_http`)."""
    from web3 import HTTPProvider

    from . import bounded_http

    parts = urlsplit(url)
    target = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")

    class DeadlineHTTPProvider(HTTPProvider):
        def _make_request(self, method: str, request_data: bytes) -> bytes:
            left = retry.time_left()
            until = time.monotonic() + (timeout if left is None else max(0.05, min(timeout, left)))
            headers = dict(self.get_request_headers())
            try:
                status, body = bounded_http.post(url, target, request_data, headers, until=until,
                                                 timeout=timeout, max_body=MAX_RPC_ANSWER_BYTES,
                                                 what=f"JSON-RPC {method}")
            except bounded_http.BodyTooLarge as exc:
                raise MalformedAnswer(str(exc)) from None
            except http.client.HTTPException as exc:  # a status line or headers http.client refuses
                if isinstance(exc, ConnectionError | http.client.IncompleteRead):
                    raise  # a broken connection (the answer may be lost, not wrong): retried or resumed
                why = f"{type(exc).__name__}: {printable(str(exc), 200)}"
                raise MalformedAnswer(f"JSON-RPC {method}: the node at {url} answered with a malformed HTTP "
                                      f"response ({why})") from None
            if status != 200:
                raise ConnectionError(f"JSON-RPC {method}: the node at {url} answered HTTP {status}")
            return body

        def decode_rpc_response(self, raw: bytes) -> Any:
            try:
                text = raw.decode("utf-8")
                if json_depth(text) > MAX_RPC_ANSWER_DEPTH:
                    raise ValueError(f"nests deeper than {MAX_RPC_ANSWER_DEPTH} levels")
                answer = json.loads(text)
            except (ValueError, RecursionError) as exc:
                raise MalformedAnswer(f"the node at {url} answered with malformed JSON ({exc})") from None
            if not isinstance(answer, dict | list):
                raise MalformedAnswer(f"the node at {url} answered with JSON that is not a JSON-RPC response")
            return answer

    return DeadlineHTTPProvider(url, request_kwargs={"timeout": timeout}, exception_retry_configuration=None)


#: The options of a RetryPolicy a ChainClient's constructors take.
RETRY_OPTIONS = ("retries", "backoff", "deadline", "is_transient", "clock", "sleep")


class RetryPolicy:
    """One total deadline per chain call, retries and backoff included (a ChainClient's).

    ``deadline``: seconds one call may take in all; ``retries``: most extra attempts within it;
    ``backoff``: the first pause between attempts, doubled after each; ``is_transient``: whether an
    error is worth another attempt; ``clock`` and ``sleep``: the time (seconds) and the pause.
    """

    def __init__(self, *, retries: int = 3, backoff: float = 0.25, deadline: float = DEFAULT_DEADLINE,
                 is_transient: Callable[[BaseException], bool] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Any] = time.sleep) -> None:
        if not (isinstance(deadline, int | float) and 0 < deadline < float("inf")):
            raise ValueError(f"deadline must be a positive number of seconds, got {deadline!r}")
        self.retries = retries
        self.backoff = backoff
        self.deadline = float(deadline)
        self.is_transient = is_transient or _is_transient
        self.clock = clock
        self.sleep = sleep
        self._until: float | None = None

    @contextlib.contextmanager
    def window(self) -> Iterator[None]:
        """One chain call: operations nested in it share the outermost one's deadline."""
        outer = self._until is None
        if outer:
            self._until = self.clock() + self.deadline
        try:
            yield
        finally:
            if outer:
                self._until = None

    def time_left(self) -> float | None:
        """Seconds left of the current call's deadline (None outside a call)."""
        return None if self._until is None else self._until - self.clock()

    def expired(self) -> bool:
        left = self.time_left()
        return left is not None and left <= 0

    def pause(self, attempt: int) -> None:
        """Back off before the next attempt, never past the deadline."""
        left = self.time_left()
        delay = self.backoff * 2**attempt
        self.sleep(max(0.0, delay if left is None else min(delay, left)))

    def call(self, op: Callable[[], Any], what: str) -> Any:
        """``op()``, tried again after each transient error while attempts and time are left."""
        last: BaseException | None = None
        with self.window():
            for attempt in range(self.retries + 1):
                try:
                    return op()
                except Exception as exc:
                    if not self.is_transient(exc):
                        raise
                    last = exc
                if self.expired():
                    raise ChainError(f"could not {what} within the {self.deadline:g} s deadline: {last}")
                if attempt < self.retries:
                    self.pause(attempt)
        raise ChainError(f"could not {what} after {self.retries + 1} attempts: {last}")


class ChainClient:
    """Signs and sends transactions to the MEDC contracts; reads their state.

    Use :meth:`embedded` or :meth:`connect` rather than the constructor. ``retry``: the
    :class:`RetryPolicy` of its calls, or ``retry_options`` for one (``deadline``: the total time
    in seconds one call may take, retries included; ``retries`` caps the attempts within it;
    ``backoff``).
    """

    def __init__(self, w3: Web3, private_keys: Sequence[str], *, description: str,
                 receipt_timeout: float = 120.0, retry: RetryPolicy | None = None,
                 **retry_options: Any) -> None:
        if not private_keys:
            raise ValueError("at least one private key is needed to sign transactions")
        if retry is not None and retry_options:
            raise TypeError(f"pass a retry policy or its options, not both ({', '.join(retry_options)})")
        self.retry = retry if retry is not None else RetryPolicy(**retry_options)
        self.w3 = w3
        self.accounts = [Account.from_key(k) for k in private_keys]
        self.description = description
        #: Sends signed bytes and waits for their receipt.
        self.txs = TxSender(w3, self.retry, receipt_timeout)
        #: When set, transactions use this gas limit after a revert check by eth_call.
        self.fixed_gas: int | None = None

    # ------------------------------------------------------------ construction
    @classmethod
    def embedded(cls, **kwargs: Any) -> ChainClient:
        """An in-process eth-tester (py-evm) chain with ten funded accounts. Nothing persists."""
        from web3 import EthereumTesterProvider

        provider = EthereumTesterProvider()
        w3 = Web3(provider)
        keys = [k.to_hex() for k in provider.ethereum_tester.backend.account_keys]
        client = cls(w3, keys, description="embedded eth-tester (py-evm, in process)", **kwargs)
        # eth-tester estimates gas by bisection (a dozen EVM runs per transaction); one eth_call
        # finds reverts just as well, and a fixed limit is free on this private chain.
        client.fixed_gas = 12_000_000
        return client

    @classmethod
    def connect(
        cls, url: str, private_keys: Sequence[str], *, poa: bool = False, timeout: float = 30.0, **kwargs: Any
    ) -> ChainClient:
        """A JSON-RPC node at ``url`` (http/https), signing locally with ``private_keys``.

        ``poa=True`` for consortium chains (Besu/Quorum clique, IBFT 2.0, QBFT) whose block
        ``extraData`` is longer than Ethereum's 32 bytes.
        """
        from web3.middleware import ExtraDataToPOAMiddleware

        if not url.startswith(("http://", "https://")):
            raise ValueError(f"JSON-RPC URL must start with http:// or https://, got {url!r}")
        retry = kwargs.pop("retry", None)
        if retry is None:  # the policy's options, if any, are the client's
            retry = RetryPolicy(**{k: kwargs.pop(k) for k in RETRY_OPTIONS if k in kwargs})
        w3 = Web3(_deadline_provider(url, timeout, retry))
        if poa:
            w3.middleware_onion.inject(ExtraDataToPOAMiddleware, layer=0)
        client = cls(w3, private_keys, description=f"JSON-RPC {url}" + (" (PoA)" if poa else ""), retry=retry,
                     **kwargs)
        retry.call(lambda: w3.eth.chain_id, f"reach the node at {url}")
        return client

    # ------------------------------------------------------------ accounts
    @property
    def addresses(self) -> list[str]:
        """Checksummed addresses of the signing accounts."""
        return [a.address for a in self.accounts]

    def account(self, who: int | str) -> Any:
        """The signing account by index or address."""
        if isinstance(who, int):
            if not 0 <= who < len(self.accounts):
                raise ValueError(f"account index {who} out of range (0..{len(self.accounts) - 1})")
            return self.accounts[who]
        addr = to_checksum_address(who)
        for acct in self.accounts:
            if acct.address == addr:
                return acct
        raise ValueError(f"no private key for {addr}")

    def balance(self, address: str) -> int:
        """Balance in wei."""
        return self.retry.call(lambda: self.w3.eth.get_balance(to_checksum_address(address)),
                               "read a balance")

    # ------------------------------------------------------------ contracts
    def contract(self, name: str, address: str | None = None) -> Any:
        """A web3 contract object for artifact ``name`` (at ``address`` when given)."""
        art = load_artifact(name)
        if address is None:
            return self.w3.eth.contract(abi=art["abi"], bytecode=art["bytecode"])
        return self.w3.eth.contract(address=to_checksum_address(address), abi=art["abi"])

    def deploy(self, name: str, *args: Any, sender: int | str = 0) -> TxResult:
        """Deploy artifact ``name`` with constructor ``args``; ``contract_address`` is set."""
        result = self.transact(self.contract(name).constructor(*args), sender=sender)
        if not result.contract_address:
            raise ChainError(f"deploying {name} produced no contract address")
        return result

    def has_code(self, address: str) -> bool:
        """Whether a contract is deployed at ``address``."""
        code = self.retry.call(lambda: self.w3.eth.get_code(to_checksum_address(address)), "read code")
        return len(code) > 0

    def call(self, fn: Any, sender: int | str | None = None, value: int = 0) -> Any:
        """Run a view / simulated call; reverts raise :class:`ContractRevert`."""
        tx: dict[str, Any] = {}
        if sender is not None:
            tx["from"] = self.account(sender).address
        if value:
            tx["value"] = value
        try:
            return self.retry.call(lambda: fn.call(tx), "call a contract")
        except ChainError:
            raise
        except Exception as exc:
            raise _refusal(exc, "a contract call") from None

    def transact(self, fn: Any, sender: int | str = 0, value: int = 0, gas: int | None = None) -> TxResult:
        """Sign, send and wait for ``fn`` (a contract function or constructor call).

        The revert check runs first (gas estimation, or an eth_call on the embedded chain), so a
        failing call raises :class:`ContractRevert` without spending anything. Transient node
        failures are retried with the same signed transaction. One deadline covers it all.
        """
        with self.retry.window():
            signed = self.sign(fn, sender, value, gas)
            return self.send_raw(signed.raw, fn=fn, sender=signed.sender, value=value)

    def sign(self, fn: Any, sender: int | str = 0, value: int = 0, gas: int | None = None) -> SignedTx:
        """Check ``fn`` for a revert, then build and sign it (nothing is sent)."""
        with self.retry.window():
            return self._sign(fn, sender, value, gas)

    def _sign(self, fn: Any, sender: int | str, value: int, gas: int | None) -> SignedTx:
        acct = self.account(sender)
        params: dict[str, Any] = {"from": acct.address, "value": value}
        if gas is None and self.fixed_gas is not None:
            if hasattr(fn, "call"):
                self.call(fn, sender=acct.address, value=value)
            gas = self.fixed_gas
        try:
            params["nonce"] = self.retry.call(
                lambda: self.w3.eth.get_transaction_count(acct.address, "pending"), "read the nonce"
            )
            params["chainId"] = self.retry.call(lambda: self.w3.eth.chain_id, "read the chain id")
            if gas is not None:
                params["gas"] = gas
            tx = self.retry.call(lambda: fn.build_transaction(params), "prepare a transaction")
        except ChainError:
            raise
        except Exception as exc:
            raise _refusal(exc, "preparing a transaction") from None
        if "gas" not in params:
            # Estimation is exact for this state; headroom covers state that changes before mining.
            tx["gas"] = int(tx["gas"] * 1.25) + 20_000
        raw = acct.sign_transaction(tx).raw_transaction
        return SignedTx(bytes(raw), "0x" + keccak(raw).hex(), tx["nonce"], acct.address, value)

    def send_raw(self, raw: bytes, fn: Any = None, sender: str | None = None, value: int = 0) -> TxResult:
        """Send signed bytes (re-sent unchanged on transient failures) and wait for the receipt."""
        with self.retry.window():
            return self.txs.send(bytes(raw), fn, sender, value)

    def lookup(
        self, tx_hash: str, fn: Any = None, sender: str | None = None, value: int = 0
    ) -> str | TxResult:
        """Where transaction ``tx_hash`` stands: its :class:`TxResult` once mined, ``"pending"``
        while the node holds it unmined, ``"unknown"`` when the node has never seen it (or lost
        it). A mined transaction that reverted raises its :class:`ContractRevert`.
        """
        with self.retry.window():
            receipt = self.retry.call(lambda: self.txs.receipt_or_none(tx_hash, quiet=False),
                                      "look up a receipt")
            if receipt is not None:
                return self.txs.result(receipt, fn, sender, value)

            def pending() -> bool:
                try:
                    self.w3.eth.get_transaction(tx_hash)
                except TransactionNotFound:
                    return False
                return True

            return "pending" if self.retry.call(pending, "look up a transaction") else "unknown"

    def chain_id(self) -> int:
        """The chain's id."""
        return self.retry.call(lambda: self.w3.eth.chain_id, "read the chain id")

    def block_number(self) -> int:
        """The latest block's number."""
        return self.retry.call(lambda: self.w3.eth.block_number, "read the block number")

    def receipt(self, tx_hash: str | bytes) -> Any:
        """The receipt of mined transaction ``tx_hash`` (ChainError when there is none)."""
        receipt = self.retry.call(lambda: self.txs.receipt_or_none(tx_hash, quiet=False), "read a receipt")
        if receipt is None:
            raise ChainError(f"no receipt for transaction {tx_hash!r}")
        return receipt

    def logs(self, event: Any, from_block: int, to_block: int | str = "latest", **filters: Any) -> list[Any]:
        """The logs of contract event ``event`` (e.g. ``contract.events.Withdrawn``) mined in the
        blocks ``from_block`` to ``to_block``, whose indexed arguments equal ``filters``."""
        return self.retry.call(
            lambda: event().get_logs(argument_filters=filters, from_block=from_block, to_block=to_block),
            "read the contract's logs",
        )

    def pending_nonce(self, address: str) -> int:
        """The next nonce the node would accept from ``address``."""
        return self.retry.call(
            lambda: self.w3.eth.get_transaction_count(to_checksum_address(address), "pending"),
            "read the nonce",
        )


class TxSender:
    """Sends signed transaction bytes and waits for their receipt, re-sending the same bytes after a
    transient failure (a retry can never pay twice: the nonce is fixed), within the current call
    of ``retry``; a reverted transaction becomes its :class:`ContractRevert`."""

    def __init__(self, w3: Web3, retry: RetryPolicy, receipt_timeout: float = 120.0) -> None:
        """``receipt_timeout``: the longest wait for one receipt (cut to what is left of the call)."""
        self.w3 = w3
        self.retry = retry
        self.receipt_timeout = receipt_timeout

    def send(self, raw: bytes, fn: Any, sender: str | None, value: int) -> TxResult:
        """Send ``raw`` (the transaction of ``fn`` by ``sender``, paying ``value``) and wait for it."""
        tx_hash = "0x" + keccak(raw).hex()
        last: BaseException | None = None
        for attempt in range(self.retry.retries + 1):
            if attempt and self.retry.expired():
                break
            try:
                self.w3.eth.send_raw_transaction(raw)
            except Exception as exc:
                msg = str(exc).lower()
                # Already in the pool or mined by an earlier attempt (the same signed bytes): fine,
                # go on to the receipt. Anything else transient: wait and re-send the same bytes.
                mined = self.receipt_or_none(tx_hash) is not None
                if not mined and not any(s in msg for s in _ALREADY_SENT):
                    if not self.retry.is_transient(exc):
                        revert = decode_revert(exc)
                        if revert is not None:
                            raise revert from None
                        raise ChainError(f"transaction rejected by the node: {exc}") from None
                    last = exc
                    self.retry.pause(attempt)
                    if self.receipt_or_none(tx_hash) is None:
                        continue
            try:
                wait = min(self.receipt_timeout, max(0.1, self.retry.time_left() or self.receipt_timeout))
                receipt = self.w3.eth.wait_for_transaction_receipt(tx_hash, timeout=wait, poll_latency=0.1)
            except Exception as exc:
                if not self.retry.is_transient(exc):
                    raise
                last = exc
                self.retry.pause(attempt)
                receipt = self.receipt_or_none(tx_hash)
                if receipt is None:
                    continue
            return self.result(receipt, fn, sender, value)
        raise ChainError(
            f"transaction {tx_hash} not confirmed within the {self.retry.deadline:g} s deadline "
            f"({self.retry.retries + 1} attempts at most; last error: {last})"
        )

    def result(self, receipt: Any, fn: Any, sender: str | None, value: int) -> TxResult:
        """The TxResult of a mined ``receipt`` (its ContractRevert or a ChainError when it failed)."""
        if receipt["status"] != 1:
            raise self._failure(receipt, fn, sender, value)
        address = receipt.get("contractAddress")
        tx_hash = "0x" + bytes(receipt["transactionHash"]).hex()
        return TxResult(tx_hash, receipt["gasUsed"], receipt["blockNumber"], receipt, address)

    def receipt_or_none(self, tx_hash: str, quiet: bool = True) -> Any:
        """The receipt of ``tx_hash``, or None while it is not mined (or, ``quiet``, unreachable)."""
        try:
            return self.w3.eth.get_transaction_receipt(tx_hash)
        except TransactionNotFound:
            return None
        except Exception as exc:
            if quiet and self.retry.is_transient(exc):
                return None
            raise

    def _failure(self, receipt: Any, fn: Any, sender: str | None, value: int) -> ChainError:
        if fn is not None and sender is not None and hasattr(fn, "call"):
            try:
                fn.call({"from": sender, "value": value}, block_identifier=receipt["blockNumber"] - 1)
            except Exception as exc:
                revert = decode_revert(exc)
                if revert is not None:
                    return revert
        return ChainError(f"transaction {receipt['transactionHash'].hex()} reverted (out of gas or revert)")

