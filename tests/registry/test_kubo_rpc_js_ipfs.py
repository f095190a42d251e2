"""The Kubo RPC backend against a real IPFS daemon (js-ipfs, same /api/v0 API), loopback only."""

from __future__ import annotations

import os

import httpx
import pytest
from medc_registry import ContentNotFoundError, KuboContentStore, Registry, compute_cid
from medc_registry.nodes import NodeError, start_js_ipfs
from registry_helpers import APP, PRICE

pytestmark = pytest.mark.ipfs


@pytest.fixture(scope="session")
def ipfs(tmp_path_factory):
    try:
        node = start_js_ipfs(tmp_path_factory.mktemp("jsipfs"))
    except NodeError as exc:
        pytest.fail(f"js-ipfs must run here (tools/node_modules): {exc}")
    store = KuboContentStore(node.url, timeout=60)
    yield store
    store.close()
    node.stop()


@pytest.mark.timing
@pytest.mark.parametrize("version", [0, 1])
def test_daemon_cids_equal_local_cids(ipfs, version):
    for data in (b"", b"hello world\n", bytes(1_048_576), os.urandom(3 * 262_144 + 7)):
        cid = ipfs.add(data, version)  # add() itself raises if the node's CID differs
        assert cid == compute_cid(data, version)
        assert ipfs.fetch(cid) == data
        assert ipfs.has(cid)
        ipfs.pin(cid)


@pytest.mark.timing
@pytest.mark.slow
@pytest.mark.parametrize("version", [0, 1])
def test_50_mb_multi_level_dag_matches_the_daemon(ipfs, version):
    data = os.urandom(50_000_000)  # 191 chunks: two levels of links
    cid = ipfs.add(data, version)
    assert cid == compute_cid(data, version)
    assert ipfs.fetch(cid) == data


@pytest.mark.timing
def test_fetch_of_unknown_content_times_out_clearly(ipfs):
    quick = KuboContentStore(ipfs.api_url, timeout=2)
    try:
        absent = compute_cid(b"nobody has these bytes " + os.urandom(16))
        assert not quick.has(absent)
        with pytest.raises(ContentNotFoundError, match="did not answer"):
            quick.fetch(absent)
    finally:
        quick.close()


@pytest.mark.timing
def test_registry_flow_with_the_ipfs_store(ipfs, embedded_chain):
    chain, dep = embedded_chain
    tester = chain.w3.provider.ethereum_tester
    snap = tester.take_snapshot()
    try:
        reg = Registry(chain, ipfs, dep)
        owner, requester = reg.as_user(1), reg.as_user(2)
        owner.register_user()
        requester.register_user()
        bundle = os.urandom(300_000)
        owner.share_model(bundle, APP, {"agents": 2, "walls": 2}, PRICE, cid_version=1)
        alloc = requester.request_models(APP, {"agents": 2, "walls": 2})[0]
        assert alloc.cid.startswith("bafybei")
        assert requester.fetch(alloc.cid) == bundle
    finally:
        tester.revert_to_snapshot(snap)


@pytest.mark.timing
def test_content_with_another_layout_is_verified_block_by_block(ipfs):
    # Another chunker gives a CID that Kubo's default layout does not reproduce: the store reads
    # the DAG with block/get and checks every block against the CID that links to it.
    data = os.urandom(5000)
    resp = httpx.post(
        f"{ipfs.api_url}/api/v0/add", params={"chunker": "size-1024", "quieter": "true"}, files={"file": data}
    )
    cid = resp.json()["Hash"]
    assert cid != compute_cid(data, 0)
    assert ipfs.fetch(cid) == data
