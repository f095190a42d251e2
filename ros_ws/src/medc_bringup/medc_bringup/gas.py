"""medc-gas-report: gas used by every contract function, next to the paper's Table III.

An offline measurement (nothing at run time imports it): ``medc-gas-report`` prints Markdown
tables, ``medc-gas-report --json`` one JSON object.

Measured on the embedded eth-tester chain (py-evm); every figure is a transaction's ``gasUsed``
(21,000 intrinsic gas included, as in the paper's table). ``updateInfo`` and ``updateReputation``
are only callable by the bound manager contract; they are measured as their own transactions on
a second Users Manager bound to an externally owned account, so each row is one call as the paper
lists it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from typing import Any

from medc_registry.chain import ChainClient
from medc_registry.registry import MAX_CANDIDATES, deploy_contracts
from medc_training.envs.names import DEFAULT_APPLICATION
from medc_training.qos import ONE

#: The paper's Table III (gas).
PAPER_GAS = {
    "UsersManager deployment": 433_933,
    "addUser": 35_857,
    "updateInfo": 67_582,
    "updateReputation": 77_286,
    "ModelsManager deployment": 1_557_311,
    "addModel": 287_448,
    "allocateModels": 43_842,
    "updateModelRep": 79_374,
}

#: Representative arguments: a CIDv0 (46 characters), two features, the description the
#: Registry facade writes for them.
APPLICATION = DEFAULT_APPLICATION
CID = "QmT78zSuBmuS4z925WZfrqQ1qHaJ56DQaTfyMUF7F8ff5o"
DESCRIPTION = '{"features":["agents","walls"]}'
CANDIDATES = (1, 8, 32, 128, MAX_CANDIDATES + 1)

_REQUEST_IDS = (i.to_bytes(32, "big") for i in itertools.count(1))


def _request_id() -> bytes:
    """A fresh non-zero idempotency key for each measured allocation."""
    return next(_REQUEST_IDS)


def evm_fork(chain: ChainClient) -> str:
    """Name of the fork the chain runs now (eth-tester: the py-evm VM class)."""
    provider = chain.w3.provider
    tester = getattr(provider, "ethereum_tester", None)
    if tester is not None:
        vm = type(tester.backend.chain.get_vm()).__name__
        return vm.removesuffix("VM")
    return "unknown (remote node)"


def measure(candidates: tuple[int, ...] = CANDIDATES) -> dict[str, Any]:
    """Deploy fresh contracts on an embedded chain and measure every function's gas."""
    chain = ChainClient.embedded()
    dep = deploy_contracts(chain)
    umc = chain.contract("UsersManager", dep.users)
    mmc = chain.contract("ModelsManager", dep.models)
    rows: dict[str, int] = {
        "UsersManager deployment": dep.gas["UsersManager"],
        "ModelsManager deployment": dep.gas["ModelsManager"],
    }
    owner, requester = 1, 2
    rows["addUser"] = chain.transact(umc.functions.addUser(), sender=owner).gas_used
    chain.transact(umc.functions.addUser(), sender=requester)
    first = chain.transact(
        mmc.functions.addModel(APPLICATION, CID, DESCRIPTION, [1, 3], 10**15), sender=owner
    )
    rows["addModel (first model of an application)"] = first.gas_used
    rows["addModel"] = chain.transact(
        mmc.functions.addModel(APPLICATION, CID, DESCRIPTION, [3, 2], 10**15), sender=owner
    ).gas_used
    alloc = chain.transact(
        mmc.functions.allocateModels(_request_id(), APPLICATION, [3, 2], [], 1, 0, 0, [0, 1]),
        sender=requester,
        value=10**15,
    )
    rows["allocateModels"] = alloc.gas_used
    rows["updateModelRep"] = chain.transact(
        mmc.functions.updateModelRep(0, ONE * 9 // 10), sender=requester
    ).gas_used
    rows["withdraw"] = chain.transact(mmc.functions.withdraw(), sender=owner).gas_used

    # updateInfo / updateReputation as stand-alone calls (manager = an externally owned account).
    solo = chain.contract("UsersManager", chain.deploy("UsersManager", sender=3).contract_address)
    chain.transact(solo.functions.setManager(chain.addresses[3]), sender=3)
    chain.transact(solo.functions.addUser(), sender=owner)
    rows["updateInfo"] = chain.transact(
        solo.functions.updateInfo(chain.addresses[owner], 1), sender=3
    ).gas_used
    rows["updateReputation"] = chain.transact(
        solo.functions.updateReputation(chain.addresses[owner], ONE * 9 // 10), sender=3
    ).gas_used

    scaling = _allocation_scaling(candidates)
    return {
        "fork": evm_fork(chain),
        "chain": chain.description,
        "rows": rows,
        "paper": PAPER_GAS,
        "allocate_scaling": scaling,
    }


def _allocation_scaling(candidates: tuple[int, ...]) -> list[dict[str, int | None]]:
    """allocateModels' gas as the number of shared models of the application grows.

    Two ways to call it: ``scan`` (every model of the application passed as a candidate, as
    before; refused above MAX_CANDIDATES models, so one call's cost is bounded), and ``ranked``
    (the Registry's way: the best ``count`` ids, found by simulating the call page by page, are
    the candidates, so the cost does not depend on how many models were shared). ``None`` marks
    a scan the contract refuses (TooManyCandidates).
    """
    from medc_registry.registry import Deployment, Registry

    chain = ChainClient.embedded()
    dep = deploy_contracts(chain)
    umc = chain.contract("UsersManager", dep.users)
    mmc = chain.contract("ModelsManager", dep.models)
    owners = [1, 2, 3, 4]
    requester = Registry(chain, None, Deployment(dep.users, dep.models), 9)  # ranks, never stores
    for i in [*owners, 9]:
        chain.transact(umc.functions.addUser(), sender=i)
    out = []
    shared = 0
    for n in sorted(candidates):
        while shared < n:
            # Varied environments and owners so the ranking does real work.
            env = [1 + shared % 4, shared % 5]
            chain.transact(
                mmc.functions.addModel(APPLICATION, CID, DESCRIPTION, env, 10**15), sender=owners[shared % 4]
            )
            shared += 1
        row: dict[str, int | None] = {"candidates": n, "count_8": min(n, 8)}
        for key, count, ranked in (
            ("allocate_1", 1, False),
            ("allocate_min_n_8", min(n, 8), False),
            ("ranked_1", 1, True),
            ("ranked_min_n_8", min(n, 8), True),
        ):
            if ranked:
                candidates = sorted(requester.rank(APPLICATION, [3, 2], count=count))  # ids = positions here
            else:
                candidates = list(range(n)) if n <= MAX_CANDIDATES else None
            row[key] = None if candidates is None else _allocation_gas(chain, mmc, count, candidates)
        out.append(row)
    return out


def _allocation_gas(chain: ChainClient, mmc, count: int, candidates: list[int]) -> int:
    """gasUsed of one allocation of ``count`` models by account 9, on a snapshot of the state."""
    # A snapshot keeps each measurement on the same state (no earlier allocation written).
    tester = chain.w3.provider.ethereum_tester
    snap = tester.take_snapshot()
    try:
        fn = mmc.functions.allocateModels(_request_id(), APPLICATION, [3, 2], [], count, 0, 0, candidates)
        return chain.transact(fn, sender=9, value=count * 10**15).gas_used
    finally:
        tester.revert_to_snapshot(snap)


def format_report(report: dict[str, Any]) -> str:
    """The report as a Markdown table plus the scaling table."""
    lines = [
        f"Gas used per transaction (gasUsed, 21,000 intrinsic included) on {report['chain']}, "
        f"EVM fork {report['fork']}; contracts compiled for evmVersion cancun.",
        "",
        "| Contract | Function | MEDC (this repo) | Paper Table III |",
        "|---|---|---:|---:|",
    ]
    order = [
        ("UMC", "deployment", "UsersManager deployment"),
        ("UMC", "addUser()", "addUser"),
        ("UMC", "updateInfo()", "updateInfo"),
        ("UMC", "updateReputation()", "updateReputation"),
        ("MMC", "deployment", "ModelsManager deployment"),
        ("MMC", "addModel()", "addModel"),
        ("MMC", "addModel(), first of an application", "addModel (first model of an application)"),
        ("MMC", "allocateModels(), 1 of 2 shared", "allocateModels"),
        ("MMC", "updateModelRep()", "updateModelRep"),
        ("MMC", "withdraw()", "withdraw"),
    ]
    for contract, fn, key in order:
        paper = report["paper"].get(key)
        lines.append(f"| {contract} | {fn} | {report['rows'][key]:,} | {f'{paper:,}' if paper else '-'} |")
    lines += [
        "",
        "allocateModels as an application's models grow. Scan: every model is a candidate (the "
        f"contract refuses more than {MAX_CANDIDATES}: TooManyCandidates). Ranked: the Registry "
        "passes the best `count`, found by simulating the call (eth_call) page by page.",
        "",
        "| Shared models | scan, count=1 | per extra candidate | scan, count | ranked, count=1 "
        "| ranked, count |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    prev = None

    def fmt(value: int | None) -> str:
        return "refused" if value is None else f"{value:,}"

    for row in report["allocate_scaling"]:
        per = "-"
        if prev is not None and row["allocate_1"] is not None and prev["allocate_1"] is not None:
            per = (
                f"{(row['allocate_1'] - prev['allocate_1']) / (row['candidates'] - prev['candidates']):,.0f}"
            )
        lines.append(
            f"| {row['candidates']} | {fmt(row['allocate_1'])} | {per} | "
            f"{fmt(row['allocate_min_n_8'])} (count={row['count_8']}) | {fmt(row['ranked_1'])} | "
            f"{fmt(row['ranked_min_n_8'])} (count={row['count_8']}) |"
        )
        prev = row
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-gas-report``: print the report (Markdown, or one JSON object)."""
    parser = argparse.ArgumentParser(prog="medc-gas-report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="one JSON object instead of tables")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    report = measure()
    print(json.dumps(report) if args.json else format_report(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
