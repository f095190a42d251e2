"""Fixtures for the registry tests: one embedded chain per session, reverted after every test."""

from __future__ import annotations

import pytest
from medc_registry import ChainClient, LocalContentStore, Registry, deploy_contracts


@pytest.fixture(scope="session")
def embedded_chain():
    """(chain, deployment) on an in-process eth-tester chain, deployed once."""
    chain = ChainClient.embedded()
    return chain, deploy_contracts(chain)


@pytest.fixture
def registry(embedded_chain, tmp_path):
    """A Registry (account 0) on the session chain; the chain is reverted after the test."""
    chain, dep = embedded_chain
    tester = chain.w3.provider.ethereum_tester
    snap = tester.take_snapshot()
    try:
        yield Registry(chain, LocalContentStore(tmp_path / "store"), dep, 0)
    finally:
        tester.revert_to_snapshot(snap)


@pytest.fixture
def users(registry):
    """Registered users: accounts 1..4 (owners and requesters)."""
    out = [registry.as_user(i) for i in range(1, 5)]
    for u in out:
        u.register_user()
    return out
