"""The full registry flow against a real anvil node over HTTP, node restarts, and the CLI's state."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
from medc_bringup.gas import APPLICATION, CID, DESCRIPTION
from medc_registry import ChainClient, LocalContentStore, Registry, deploy_contracts
from medc_registry.chain import ChainError, ContractRevert
from medc_registry.cli import main as cli_main
from medc_registry.nodes import NodeError, free_port, start_anvil
from registry_helpers import APP, PRICE

pytestmark = pytest.mark.anvil


@pytest.fixture(scope="module")
def anvil(tmp_path_factory):
    try:
        node = start_anvil(tmp_path_factory.mktemp("anvil"))
    except NodeError as exc:
        pytest.fail(f"anvil must run here (tools/node_modules): {exc}")
    yield node
    node.stop()


@pytest.mark.timing
def test_full_flow_over_json_rpc_with_poa_middleware(anvil, tmp_path):
    chain = ChainClient.connect(anvil.url, anvil.extra["private_keys"], poa=True)
    reg = Registry(chain, LocalContentStore(tmp_path), deploy_contracts(chain))
    owner, requester = reg.as_user(1), reg.as_user(2)
    owner.register_user()
    requester.register_user()
    bundle = b"expert weights" * 1000
    shared = owner.share_model(bundle, APP, {"agents": 1, "walls": 3}, PRICE)
    allocs = requester.request_models(APP, {"agents": 3, "walls": 2}, count=2)
    assert [a.model_id for a in allocs] == [shared.model_id]
    assert requester.fetch(allocs[0].cid) == bundle
    requester.review(allocs[0].allocation_id, 0.75)
    with pytest.raises(ContractRevert) as exc:  # custom errors decoded from the node's JSON-RPC error
        requester.review(allocs[0].allocation_id, 0.75)
    assert exc.value.error == "AlreadyReviewed"
    assert owner.user().reputation == pytest.approx(0.75)
    assert owner.withdraw() == PRICE
    assert chain.balance(reg.deployment.models) == 0


@pytest.mark.timing
def test_resending_the_same_signed_payment_pays_once(anvil, tmp_path):
    chain = ChainClient.connect(anvil.url, anvil.extra["private_keys"])
    reg = Registry(chain, LocalContentStore(tmp_path), deploy_contracts(chain))
    for i in (3, 4):
        reg.as_user(i).register_user()
    reg.as_user(3).share_model(b"m", APP, {"agents": 1, "walls": 1}, PRICE)
    requester = chain.account(4)
    fn = reg.models.functions.allocateModels(b"\x01" * 32, APP, [1, 1], [], 1, 0, 0, [0])
    tx = fn.build_transaction(
        {
            "from": requester.address,
            "value": PRICE,
            "nonce": chain.w3.eth.get_transaction_count(requester.address),
        }
    )
    raw = requester.sign_transaction(tx).raw_transaction
    first = chain.send_raw(raw)
    again = chain.send_raw(raw)  # what a retry after a lost answer does
    assert first.tx_hash == again.tx_hash
    assert reg.owed(chain.addresses[3]) == PRICE
    assert chain.call(reg.models.functions.allocationCount()) == 1


@pytest.mark.timing
def test_transaction_survives_a_node_restart(tmp_path):
    port = free_port()
    state = tmp_path / "state.json"
    node = start_anvil(tmp_path / "a", state_file=state, port=port)
    keys = node.extra["private_keys"]
    try:
        # Retries until the node is back, however long a loaded machine takes to restart it (the
        # backoff doubles: 8 retries outlast the call's 60 s deadline).
        chain = ChainClient.connect(node.url, keys, retries=8, backoff=0.3)
        reg = Registry(chain, LocalContentStore(tmp_path / "s"), deploy_contracts(chain))
        for i in (1, 2):
            reg.as_user(i).register_user()
        reg.as_user(1).share_model(b"m", APP, {"agents": 2, "walls": 1}, PRICE)
        node.stop()  # anvil writes its state on SIGTERM
        restarted: list = []

        def restart():
            time.sleep(1.0)
            restarted.append(start_anvil(tmp_path / "b", state_file=state, port=port))

        t = threading.Thread(target=restart)
        t.start()
        allocs = reg.as_user(2).request_models(APP, {"agents": 2, "walls": 1}, payment=PRICE)
        t.join()
        node = restarted[0]
        assert len(allocs) == 1
        assert reg.owed(chain.addresses[1]) == PRICE  # paid exactly once
        assert chain.call(reg.models.functions.allocationCount()) == 1
    finally:
        node.stop()


@pytest.mark.timing
def test_unreachable_node_gives_a_clear_error():
    with pytest.raises(ChainError, match="could not reach the node"):
        ChainClient.connect(f"http://127.0.0.1:{free_port()}", ["0x" + "11" * 32], retries=1, backoff=0.05)
    with pytest.raises(ValueError, match="http"):
        ChainClient.connect("ws://127.0.0.1:1", ["0x" + "11" * 32])


def _exited(pid: int) -> bool:
    """Whether process ``pid`` has ended (a zombie its parent has not reaped yet has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] == "Z"


@pytest.mark.timing
def test_cli_state_survives_invocations_and_node_restarts(tmp_path, capsys):
    home = ["--home", str(tmp_path / "home")]
    model = tmp_path / "expert.bin"
    model.write_bytes(b"expert policy bundle bytes")
    assert cli_main([*home, "status"]) == 2
    assert "no registry configured" in capsys.readouterr().err
    with pytest.raises(RuntimeError, match="medc-registry start"):
        Registry.from_home(str(tmp_path / "home"))
    assert cli_main([*home, "start"]) == 0
    try:
        assert cli_main([*home, "register", "--account", "1"]) == 0
        assert cli_main([*home, "register", "--account", "2"]) == 0
        args = ["share", str(model), "--application", APP, "--env", "agents=1", "--env", "walls=3"]
        assert cli_main([*home, *args, "--price", "0.001", "--account", "1"]) == 0
        cid = capsys.readouterr().out.split("CID ")[1].split(",")[0]
        pid = json.loads((tmp_path / "home" / "registry.json").read_text())["node"]["pid"]
        assert cli_main([*home, "stop"]) == 0
        # stop signals the node and returns; the node writes its state as it exits.
        deadline = time.monotonic() + 60
        while not _exited(pid):
            assert time.monotonic() < deadline, f"anvil (pid {pid}) still running 60 s after stop"
            time.sleep(0.05)
        assert cli_main([*home, "start"]) == 0  # same chain state, same contracts
        assert "restarted anvil" in capsys.readouterr().out
        req = ["request", "--application", APP, "--env", "agents=3", "--env", "walls=2", "--count", "2"]
        assert cli_main([*home, *req, "--account", "2"]) == 0
        out = capsys.readouterr().out
        assert "1 model(s) allocated" in out and cid in out and "0.1667" in out
        assert cli_main([*home, "fetch", cid, "-o", str(tmp_path / "got.bin"), "--account", "2"]) == 0
        assert (tmp_path / "got.bin").read_bytes() == model.read_bytes()
        assert cli_main([*home, "review", "0", "0.8", "--account", "2"]) == 0
        assert cli_main([*home, "review", "0", "0.8", "--account", "2"]) == 2
        assert "AlreadyReviewed" in capsys.readouterr().err
        assert cli_main([*home, "withdraw", "--account", "1"]) == 0
        assert "withdrew 0.001 ETH" in capsys.readouterr().out
        assert cli_main([*home, "status", "--account", "1"]) == 0
        out = capsys.readouterr().out
        assert "reputation 0.800" in out and "1 models, 1 allocations" in out
        # The Python API opens the same recorded registry.
        owner = Registry.from_home(str(tmp_path / "home"), account=1)
        assert owner.user().reputation == pytest.approx(0.8) and owner.list_models()[0].cid == cid
    finally:
        cli_main([*home, "stop"])


@pytest.mark.timing
def test_bridge_opens_a_json_rpc_registry_through_the_home_spec(anvil, tmp_path):
    """The bridge's parameters are a spec of medc_registry.home: key file, contracts, store."""
    from medc_registry.bridge_node import BridgeError, connect_registry

    chain = ChainClient.connect(anvil.url, anvil.extra["private_keys"])
    dep = deploy_contracts(chain)
    keys = tmp_path / "bridge.key"
    keys.write_text("\n".join(anvil.extra["private_keys"][6:8]) + "\n")
    reg = connect_registry(anvil.url, str(tmp_path / "store"), dep.users, dep.models, str(keys), account=1)
    assert reg.address == chain.addresses[7] and reg.deployment.models == dep.models
    reg.register_user()
    model = reg.share_model(b"bridge bytes", APP, {"agents": 1, "walls": 2}, PRICE)
    assert (tmp_path / "store").is_dir() and reg.fetch(model.cid) == b"bridge bytes"
    with pytest.raises(BridgeError, match="no Models Manager contract at"):
        connect_registry(anvil.url, str(tmp_path / "store"), dep.users, reg.address, str(keys))
    with pytest.raises(BridgeError, match="account index 2 out of range"):
        connect_registry(anvil.url, str(tmp_path / "store"), dep.users, dep.models, str(keys), account=2)


@pytest.mark.timing
def test_cli_deploy_on_an_existing_node(anvil, tmp_path, capsys):
    keys = tmp_path / "keys.txt"
    keys.write_text("\n".join(anvil.extra["private_keys"][5:8]) + "\n")
    home = ["--home", str(tmp_path / "ext")]
    assert cli_main([*home, "deploy", "--rpc", anvil.url, "--key-file", str(keys), "--poa"]) == 0
    assert "deployed on" in capsys.readouterr().out
    assert cli_main([*home, "deploy", "--rpc", anvil.url, "--key-file", str(keys)]) == 2  # never twice
    assert cli_main([*home, "register", "--account", "1"]) == 0
    assert cli_main([*home, "status", "--json", "--account", "1"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert '"registered": true' in out and "(PoA)" in out
    assert cli_main([*home, "stop"]) == 2  # an external chain is not ours to stop
    assert "external chain" in capsys.readouterr().err


@pytest.mark.timing
def test_gas_is_the_same_on_anvil_cancun_and_eth_tester_prague(anvil, embedded_chain):
    tester = embedded_chain[0].w3.provider.ethereum_tester
    snap = tester.take_snapshot()
    try:
        figures = []
        for chain in (ChainClient.connect(anvil.url, anvil.extra["private_keys"]), embedded_chain[0]):
            dep = deploy_contracts(chain)
            umc, mmc = chain.contract("UsersManager", dep.users), chain.contract("ModelsManager", dep.models)
            gas = [dep.gas["UsersManager"], dep.gas["ModelsManager"]]
            gas.append(chain.transact(umc.functions.addUser(), sender=8).gas_used)
            chain.transact(umc.functions.addUser(), sender=9)
            add = mmc.functions.addModel(APPLICATION, CID, DESCRIPTION, [1, 3], PRICE)
            gas.append(chain.transact(add, sender=8).gas_used)
            alloc = mmc.functions.allocateModels(b"\x01" * 32, APPLICATION, [3, 2], [], 1, 0, 0, [0])
            gas.append(chain.transact(alloc, sender=9, value=PRICE).gas_used)
            figures.append(gas)
        assert figures[0] == figures[1]
    finally:
        tester.revert_to_snapshot(snap)
