"""``medc-registry``: the registry's command line, following the paper's time sequence.

State lives in a home directory (``--home``, ``$MEDC_HOME`` or ``./.medc``): ``registry.json``
records the chain (JSON-RPC URL, contract addresses), the content store and, for a node started
here, the anvil process and its state file (medc_registry.home reads and writes it). Every command
except ``start``, ``deploy`` and ``cid`` reads it and stops with a clear message when no chain is
configured — the CLI never falls back to a throwaway chain. The gas report is ``medc-gas-report``
(medc_bringup).

    medc-registry start                       # persistent local anvil + contracts + local content store
    medc-registry register --account 1
    medc-registry share model.safetensors --application target_localization \\
        --env agents=1 --env walls=3 --price 0.001 --account 1
    medc-registry request --application target_localization --env agents=3 --env walls=2 \\
        --count 2 --account 2
    medc-registry fetch CID -o expert.safetensors --account 2
    medc-registry review ALLOCATION_ID 0.8 --account 2
    medc-registry withdraw --account 1
    medc-registry status
    medc-registry stop
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import stat
import sys
import time
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

from medc_training.untrusted import printable

from .chain import DEFAULT_DEADLINE, ChainClient, ChainError
from .cid import MAX_CONTENT_BYTES, compute_cid
from .content import ContentStoreError
from .home import (
    HOME_DEADLINE,
    STATE_FILE,
    RegistryHomeError,
    home_dir,
    load_state,
    save_state,
    state_settings,
)
from .journal import LockWaitInterrupted, PendingLockTimeout, PendingRecordsError, process_start_time
from .ranker import DEFAULT_PRICE_FACTOR
from .registry import Registry, check_share_text, deploy_contracts, format_eth

#: Default total seconds for one chain call from the CLI (``--deadline``).
CLI_DEADLINE = HOME_DEADLINE


class CliError(RuntimeError):
    """A user-facing error: printed without a traceback, exit status 2."""


# ---------------------------------------------------------------- state (medc_registry.home)
def open_chain(home: Path, state: dict[str, Any], deadline: float = CLI_DEADLINE) -> ChainClient:
    """A client for the chain ``state`` records (RegistryHomeError when the node does not answer)."""
    return state_settings(home, state).open_chain(deadline)


def open_registry(args: argparse.Namespace) -> Registry:
    """The registry for ``--account`` from the recorded state."""
    return Registry.from_home(args.home, args.account, args.deadline)


# ---------------------------------------------------------------- parsing helpers
#: What an amount may be, for every message about one.
#: Longest amount text read (digits beyond this are not an amount anyone means).
MAX_AMOUNT_CHARS = 100
AMOUNT_RULE = (
    "an amount is a finite, non-negative number of ETH with at most 18 decimals (e.g. 0.001) "
    "or a whole number of wei (e.g. 1000wei), below 2**128 wei"
)


def parse_eth(text: str, what: str = "amount") -> int:
    """``"0.001"`` ETH (or ``"1000wei"``) -> wei; CliError saying what is allowed otherwise.

    Exact whatever the exponent: ``1e999999999`` is too large and ``1e-999999999`` has more than
    18 decimals, both refused before any arithmetic (no ``decimal.Overflow``, no silent 0).
    """
    text = text.strip().lower()
    if len(text) > MAX_AMOUNT_CHARS:
        raise CliError(f"{what} is over {MAX_AMOUNT_CHARS} characters: {AMOUNT_RULE}")
    try:
        if text.endswith("wei"):
            value = int(text[:-3])
        else:
            amount = Decimal(text.removesuffix("eth"))
            if not amount.is_finite():
                raise CliError(f"{what} {text!r} is not finite: {AMOUNT_RULE}")
            if amount.is_signed() and amount != 0:
                raise CliError(f"{what} {text!r} is negative: {AMOUNT_RULE}")
            value = _wei(amount, what, text)
    except (InvalidOperation, ValueError):
        raise CliError(f"{what} {printable(text, 60)!r} is not an amount: {AMOUNT_RULE}") from None
    if value < 0:
        raise CliError(f"{what} {text!r} is negative: {AMOUNT_RULE}")
    if value >= 2**128:
        raise CliError(f"{what} {text!r} is too large: {AMOUNT_RULE}")
    return value


def _wei(amount: Decimal, what: str, text: str) -> int:
    """A non-negative finite ETH amount in wei, exactly (integer arithmetic on its digits)."""
    _sign, digits, exponent = amount.as_tuple()
    number = int("".join(map(str, digits)) or "0")
    if number == 0:
        return 0
    if amount.adjusted() > 21:  # 10**22 ETH is over 2**128 wei
        raise CliError(f"{what} {text!r} is too large: {AMOUNT_RULE}")
    if amount.adjusted() < -18:
        raise CliError(f"{what} {text!r} has more than 18 decimals: {AMOUNT_RULE}")
    shift = int(exponent) + 18  # bounded by the checks above and the number of digits
    if shift >= 0:
        return number * 10**shift
    if number % 10**-shift:
        raise CliError(f"{what} {text!r} has more than 18 decimals: {AMOUNT_RULE}")
    return number // 10**-shift


def read_model_file(path: str) -> bytes:
    """The bytes of the model file ``path``: a regular file of at most the content limit, read
    without blocking (a FIFO or a device such as ``/dev/zero`` is refused before any read)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise CliError(f"cannot open {path}: {exc.strerror}") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_CONTENT_BYTES:
        os.close(fd)
        if not stat.S_ISREG(info.st_mode):
            raise CliError(f"{path} is not a regular file (a folder, FIFO or device): give the model file")
        raise CliError(f"{path} is {info.st_size} bytes, over the {MAX_CONTENT_BYTES} byte content limit")
    with os.fdopen(fd, "rb", buffering=0) as fh:
        chunks, size = [], 0
        while chunk := fh.read(1 << 20):
            size += len(chunk)
            if size > MAX_CONTENT_BYTES:
                raise CliError(f"{path} grew past the {MAX_CONTENT_BYTES} byte content limit while read")
            chunks.append(chunk)
    return b"".join(chunks)


def _show(text: object, limit: int = 200) -> str:
    """On-chain text (anyone's: application names, CIDs, feature names) safe for a terminal."""
    return printable(str(text), limit)


def parse_pairs(items: list[str] | None, kind: type, what: str) -> dict[str, Any]:
    """``["agents=3", "walls=2"]`` -> ``{"agents": 3, "walls": 2}``."""
    out: dict[str, Any] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise CliError(f"{what} must look like NAME=VALUE, got {item!r}")
        try:
            out[name] = kind(value)
        except ValueError:
            raise CliError(f"{what} {name!r}: {value!r} is not a valid {kind.__name__}") from None
    return out


def _qos(value: float) -> str:
    return "inf (exact match)" if math.isinf(value) else f"{value:.4f}"


# ---------------------------------------------------------------- commands
def cmd_start(args: argparse.Namespace) -> int:
    from .nodes import NodeError, _rpc_ready, start_anvil

    home = home_dir(args.home)
    state_path = home / STATE_FILE
    state = json.loads(state_path.read_text()) if state_path.is_file() else None
    if state and not state.get("node"):
        raise CliError(f"{home} is configured for an external chain ({state['rpc_url']}); use another --home")
    if state and _rpc_ready(state["rpc_url"]):
        print(f"already running: {state['rpc_url']} (pid {state['node']['pid']})")
        return 0
    port = args.port or (state["node"]["port"] if state else None)
    try:
        node = start_anvil(home, state_file=home / "anvil-state.json", port=port, detach=True)
    except NodeError as exc:
        if port and not args.port:
            node = start_anvil(home, state_file=home / "anvil-state.json", detach=True)
        else:
            raise CliError(str(exc)) from None
    node_info = {"pid": node.pid, "port": int(node.url.rsplit(":", 1)[1]), "state_file": "anvil-state.json"}
    if state:
        state["rpc_url"] = node.url
        state["node"] = node_info
        chain = open_chain(home, state)
        if not chain.has_code(state["models_manager"]):
            raise CliError(f"restarted the node but its saved state lost the contracts; remove {state_path}")
        save_state(home, state)
        print(f"restarted anvil at {node.url} (pid {node.pid}); contracts at {state['models_manager']}")
        return 0
    state = {"rpc_url": node.url, "poa": False, "node": node_info}
    chain = open_chain(home, state)
    dep = deploy_contracts(chain)
    record_deployment(home, state, chain, dep, args.ipfs_api)
    print(f"anvil at {node.url} (pid {node.pid}), state in {home}")
    print(f"UsersManager  {dep.users}\nModelsManager {dep.models}")
    print(f"{len(chain.accounts)} funded development accounts: use --account 0..{len(chain.accounts) - 1}")
    return 0


def record_deployment(home: Path, state: dict[str, Any], chain, dep, ipfs_api: str | None) -> None:
    """Save the freshly deployed contracts and the content store choice in the registry state."""
    local = {"kind": "local", "root": str(home / "content")}
    content = {"kind": "kubo", "url": ipfs_api} if ipfs_api else local
    state.update(
        users_manager=dep.users, models_manager=dep.models, chain_id=chain.chain_id(), content=content
    )
    save_state(home, state)


def cmd_deploy(args: argparse.Namespace) -> int:
    home = home_dir(args.home)
    if (home / STATE_FILE).exists():
        raise CliError(f"{home / STATE_FILE} exists; use another --home for a second deployment")
    key_file = str(Path(args.key_file).resolve())
    state: dict[str, Any] = {"rpc_url": args.rpc, "poa": args.poa, "key_file": key_file}
    chain = open_chain(home, state)
    dep = deploy_contracts(chain, sender=args.account)
    record_deployment(home, state, chain, dep, args.ipfs_api)
    print(f"deployed on {args.rpc}: UsersManager {dep.users}, ModelsManager {dep.models}")
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    home = home_dir(args.home)
    state = load_state(home)
    node = state.get("node")
    if not node:
        raise CliError("this registry uses an external chain; nothing to stop")
    pid = node["pid"]
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        cmdline = []
    # The pid may have been reused since `start` (e.g. after a reboot): only signal our anvil.
    if not cmdline or not cmdline[0].endswith(b"anvil") or str(home).encode() not in b" ".join(cmdline):
        print("the node was not running")
        return 0
    try:
        os.kill(pid, signal.SIGTERM)  # anvil dumps its state on SIGTERM
        print(f"stopped anvil (pid {pid}); state kept in {home}")
    except ProcessLookupError:
        print("the node was not running")
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    reg = open_registry(args)
    reg.register_user()
    print(f"registered {reg.address} (reputation {reg.user().reputation:.2f})")
    return 0


def cmd_share(args: argparse.Namespace) -> int:
    env = parse_pairs(args.env, int, "--env")
    if not env:
        raise CliError("give the environment features, e.g. --env agents=3 --env walls=2")
    price = parse_eth(args.price, "--price")  # refused before connecting
    check_share_text(args.application, args.description)
    data = read_model_file(args.file)
    reg = open_registry(args)
    m = reg.share_model(data, args.application, env, price, args.description, args.cid_version)
    print(
        f"model {m.model_id} shared: CID {_show(m.cid)}, {_show(m.application)} {_show(m.env_features)}, "
        f"price {format_eth(m.price_wei)}"
    )
    return 0


def cmd_request(args: argparse.Namespace) -> int:
    env = parse_pairs(args.env, int, "--env")
    weights = parse_pairs(args.weight, float, "--weight") or None
    payment = parse_eth(args.payment, "--payment") if args.payment else None
    max_price = parse_eth(args.max_price, "--max-price") if args.max_price else None
    max_total = parse_eth(args.max_total, "--max-total") if args.max_total else None
    reg = open_registry(args)

    def quoted(ranking) -> None:
        print(f"quote: {len(ranking.model_ids)} model(s) for {format_eth(ranking.price_wei)}; "
              f"limit {ranking.limit.describe()}", flush=True)

    try:
        allocs = reg.request_models(
            args.application,
            env,
            weights,
            args.count,
            args.min_model_rep,
            args.min_owner_rep,
            payment,
            args.request_id,
            max_price,
            max_total,
            same_since=args.started,
            on_quote=quoted,
        )
    except ChainError as exc:
        raise CliError(str(exc)) from None
    if allocs and allocs[0].replayed:
        print(
            f"already paid: request {allocs[0].request_id} was allocated and paid by an earlier run; "
            "nothing was paid again. Here is your allocation:"
        )
    print(f"{len(allocs)} model(s) allocated (request {allocs[0].request_id if allocs else '-'}):")
    print(
        f"{'alloc':>5}  {'model':>5}  {'QoS':>17}  {'D_m':>6}  {'price':>12}  {'rep':>5}  environment / CID"
    )
    for a in allocs:
        print(
            f"{a.allocation_id:>5}  {a.model_id:>5}  {_qos(a.qos):>17}  {a.distance:>6.3f}  "
            f"{format_eth(a.price_wei):>12}  {a.model.reputation:>5.2f}  {_show(a.model.env_features)} "
            f"{_show(a.cid)}"
        )
    others = reg.pending_requests()
    if others:
        print(
            f"note: {len(others)} other paid request(s) of this account are not confirmed yet "
            f"(in {reg.pending.path}); run them again to resolve them"
        )
    return 0


def cmd_fetch(args: argparse.Namespace) -> int:
    reg = open_registry(args)
    if args.output:
        size = reg.fetch_to(args.cid, args.output, overwrite=args.overwrite)
        print(f"{size} bytes verified against {args.cid} -> {args.output}")
    else:
        sys.stdout.buffer.write(reg.fetch(args.cid))
    return 0


def cmd_review(args: argparse.Namespace) -> int:
    if not 0 <= args.allocation_id < 2**256:
        raise CliError(f"allocation id {args.allocation_id} is not one: ids are 0 to 2**256 - 1")
    if not (math.isfinite(args.value) and 0.0 <= args.value <= 1.0):
        raise CliError(f"review {args.value} is not in [0, 1]")
    reg = open_registry(args)
    reg.review(args.allocation_id, args.value)
    _, model_id, _ = reg.allocation(args.allocation_id)
    m = reg.model(model_id)
    print(f"reviewed allocation {args.allocation_id}: model {model_id} reputation now {m.reputation:.3f}")
    return 0


def cmd_withdraw(args: argparse.Namespace) -> int:
    reg = open_registry(args)
    amount = reg.withdraw()
    print(f"withdrew {format_eth(amount)} to {reg.address}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    reg = open_registry(args)
    s = reg.status()
    if args.json:
        print(json.dumps(s))
        return 0
    print(f"chain          {s['chain']} (chain id {s['chain_id']}, block {s['block']})")
    print(f"contracts      UsersManager {s['users_manager']}, ModelsManager {s['models_manager']}")
    print(f"content store  {s['content_store']}")
    print(f"account        {s['account']}  balance {format_eth(s['balance_wei'])}")
    reg_text = f"reputation {s['reputation']:.3f}" if s["registered"] else "not registered"
    print(f"               {reg_text}, owed {format_eth(s['owed_wei'])}")
    print(f"registry       {s['models_shared']} models, {s['allocations']} allocations, "
          f"escrow {format_eth(s['contract_balance_wei'])}")  # fmt: skip
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    reg = open_registry(args)
    for m in reg.list_models(args.application):
        print(
            f"{m.model_id:>4}  {_show(m.application)}  {_show(m.env_features)}  rep {m.reputation:.3f} "
            f"({m.alloc_count} alloc)  {format_eth(m.price_wei)}  owner {m.owner}  {_show(m.cid)}"
        )
    return 0


def cmd_cid(args: argparse.Namespace) -> int:
    print(compute_cid(read_model_file(args.file), args.cid_version))
    return 0


def _deadline(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a positive, finite number of seconds")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    p = argparse.ArgumentParser(prog="medc-registry", description="MEDC model registry (contracts + IPFS)")
    p.add_argument("--home", help="state directory (default $MEDC_HOME or ./.medc)")
    p.add_argument(
        "--deadline",
        type=_deadline,
        default=CLI_DEADLINE,
        help=f"total seconds one chain call may take, retries included (default {CLI_DEADLINE:g}; "
        f"the Python API's default is {DEFAULT_DEADLINE:g})",
    )
    sub = p.add_subparsers(dest="command", required=True)

    def add(name: str, fn, help_: str, account: bool = True) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(func=fn)
        if account:
            sp.add_argument("--account", type=int, default=0, help="signing account index (default 0)")
        return sp

    sp = add("start", cmd_start, "start (or restart) a persistent local anvil node and deploy", account=False)
    sp.add_argument("--port", type=int, help="JSON-RPC port on 127.0.0.1 (default: a free one)")
    sp.add_argument("--ipfs-api", help="use a Kubo RPC endpoint instead of the local content store")
    sp = add("deploy", cmd_deploy, "deploy the contracts on an existing JSON-RPC chain")
    sp.add_argument("--rpc", required=True, help="JSON-RPC URL")
    sp.add_argument("--key-file", required=True, help="file with one hex private key per line")
    sp.add_argument("--poa", action="store_true", help="Besu/Quorum PoA chain (long extraData)")
    sp.add_argument("--ipfs-api", help="Kubo RPC endpoint (default: local content store)")
    add("stop", cmd_stop, "stop the local node started by `start` (its state is kept)", account=False)
    add("register", cmd_register, "register the account (addUser)")
    sp = add("share", cmd_share, "upload a model file and share it (addModel)")
    sp.add_argument("file")
    sp.add_argument("--application", required=True)
    sp.add_argument("--env", action="append", metavar="NAME=INT", help="environment feature (repeat)")
    sp.add_argument("--price", default="0", help="price per allocation in ETH (e.g. 0.001) or NNNwei")
    sp.add_argument("--description", help="free text stored with the model")
    sp.add_argument("--cid-version", type=int, choices=(0, 1), default=0)
    sp = add("request", cmd_request, "request models (allocateModels) and pay for them")
    sp.add_argument("--application", required=True)
    sp.add_argument("--env", action="append", metavar="NAME=INT", help="your environment's feature (repeat)")
    sp.add_argument("--weight", action="append", metavar="NAME=FLOAT", help="feature weight, sum 1 (repeat)")
    sp.add_argument("--count", type=int, default=1)
    sp.add_argument("--min-model-rep", type=float, default=0.0)
    sp.add_argument("--min-owner-rep", type=float, default=0.0)
    sp.add_argument("--payment", help="amount to send (default: the exact price); excess is refundable")
    sp.add_argument(
        "--max-price",
        help="the most one model may cost, in ETH or NNNwei; dearer models are passed over (default: "
        f"{DEFAULT_PRICE_FACTOR} x the cheapest non-zero price among the models the request could get, "
        "at most the account's balance; free models only when all are free)",
    )
    sp.add_argument(
        "--max-total",
        help="the most the whole request may cost, in ETH or NNNwei; a dearer quote is refused before "
        "anything is paid (default: no limit beyond --max-price per model)",
    )
    sp.add_argument(
        "--request-id",
        help="idempotency key (0x + 64 hex, or any text); default: a new one, recorded in the home "
        "with the signed payment before it is sent, so re-running the same request never pays twice",
    )
    sp = add("fetch", cmd_fetch, "download a model file, verified against its CID")
    sp.add_argument("cid")
    sp.add_argument("-o", "--output", help="file to write, atomically (default: stdout); an existing "
                    "file is refused unless --overwrite")
    sp.add_argument("--overwrite", action="store_true", help="replace a file already at --output")
    sp = add("review", cmd_review, "review an allocated model (updateModelRep)")
    sp.add_argument("allocation_id", type=int)
    sp.add_argument("value", type=float, help="review in [0, 1]")
    add("withdraw", cmd_withdraw, "withdraw payments and refunds owed to the account")
    sp = add("status", cmd_status, "show the chain, contracts and the account's standing")
    sp.add_argument("--json", action="store_true")
    sp = add("models", cmd_models, "list shared models")
    sp.add_argument("--application")
    sp = add("cid", cmd_cid, "print the CID `ipfs add --only-hash` gives for FILE", account=False)
    sp.add_argument("file")
    sp.add_argument("--cid-version", type=int, choices=(0, 1), default=0)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``medc-registry``. Run as a program (``argv`` None), its run began when its
    process started (before the interpreter loaded): an identical request another run confirmed
    since then is this one. Called with ``argv``, the run begins at the call."""
    started = process_start_time() if argv is None else time.time()
    args = build_parser().parse_args(argv)
    args.started = started
    try:
        return args.func(args)
    except (CliError, RegistryHomeError, ChainError, ContentStoreError, PendingRecordsError,
            PendingLockTimeout, ValueError, OSError) as exc:
        print(f"medc-registry {args.command}: {exc}", file=sys.stderr)
        return 2
    except LockWaitInterrupted as exc:
        print(f"medc-registry {args.command}: {exc}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        note = ("; a payment it sent is recorded in the home: run the same request again to resolve it "
                "(it never pays twice)") if args.command == "request" else ""
        print(f"medc-registry {args.command}: interrupted{note}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
