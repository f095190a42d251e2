"""Shared pytest configuration for the MEDC suites."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


def pytest_configure(config: pytest.Config) -> None:
    # Every ROS participant the tests start stays on this machine.
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


#: Test folders whose tests start ROS graphs: under pytest-xdist with ``--dist loadgroup`` (``make
#: test`` runs two workers) they run one after another on one worker, the other tests beside them
#: on the other, so no two graphs compete for the two cores.
GRAPH_FOLDERS = ("tests/ros/", "tests/e2e/")


def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """The ``loadgroup`` scheduler with the graph tests as one group. (xdist's own ``xdist_group``
    marker does not take effect under pytest 9, whose node ids it can no longer suffix.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GraphTestsTogether(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return "graph" if nodeid.startswith(GRAPH_FOLDERS) else nodeid

    return GraphTestsTogether(config, log)


@pytest.fixture
def one_thread():
    """One torch intra-op thread for the test, as an agent node and medc-radbench run (their
    ``threads``, default 1): the tensors of these tests are small, and on two busy cores a second
    thread mostly waits on the first (a layer waits for its slower thread, 10x slower under load)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _bundle_refusals_forgotten():
    """Each test starts with no bundle refusal remembered in this process (nor a pause of dry runs
    that earlier tests' slow bundles would have caused)."""
    import sys

    policy = sys.modules.get("medc_training.bundle.policy")
    if policy is not None:
        policy.forget_refusals()
    yield
