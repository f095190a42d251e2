"""Hostile bundles on the policy topics, the policy parameter and the bridge's fetch are
refused with the reason; the agent process and the bridge keep running and keep answering."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from medc_common import contract
from rclpy.parameter import Parameter
from ros_helpers import spin_until
from std_msgs.msg import String

SCENARIO = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 3}
BIN = Path(sys.executable).parent
SECRET = b"SECRET-K3y-9f8a7c6b5d4e3f2a1b0c\n"


def _hostile(directory: Path) -> dict[str, tuple[Path, str]]:
    """Hostile files for a 10x10 agent, with what their refusal says."""
    import torch
    from medc_training import bundle
    from medc_training.bundle import MANIFEST_KEY, bundle_bytes
    from medc_training.nets import make_actor_critic
    from safetensors.torch import save as st_save

    max_manifest_chars = getattr(bundle, "MAX_MANIFEST_CHARS", 65536)
    torch.manual_seed(0)
    net = make_actor_critic("lenet5", (5, 10, 10), 8)
    good = bundle_bytes(net, {"application": "target_localization", "environment": {"grid": 10}})
    n = int.from_bytes(good[:8], "little")
    manifest = json.loads(json.loads(good[8:8 + n])["__metadata__"][MANIFEST_KEY])
    tensors = dict(net.state_dict())

    def with_training(raw: str) -> bytes:
        text = json.dumps({**manifest, "training": "@@"}).replace('"@@"', raw)
        return st_save(tensors, metadata={MANIFEST_KEY: text})

    # The compute bomb at this agent's 10x10 input: padded 1x1 convolutions grow the map,
    # then one large convolution; 17 k parameters.
    layers = [{"type": "conv2d", "out_channels": 1, "kernel_size": 1, "stride": 1, "padding": 64}] * 3
    layers = [*layers, {"type": "conv2d", "out_channels": 16, "kernel_size": 64, "stride": 1, "padding": 0},
              {"type": "maxpool2d", "kernel_size": 64, "stride": 64, "ceil_mode": True},
              {"type": "flatten"}, {"type": "heads", "num_actions": 8}]
    spec = {"name": "bomb", "input": {"channels": 5, "height": 10, "width": 10}, "layers": layers}
    bomb_tensors = {f"trunk.{i}.weight": torch.zeros(1, 5 if i == 0 else 1, 1, 1) for i in range(3)}
    bomb_tensors.update({f"trunk.{i}.bias": torch.zeros(1) for i in range(3)})
    bomb_tensors.update({"trunk.3.weight": torch.zeros(16, 1, 64, 64), "trunk.3.bias": torch.zeros(16),
                         "policy.weight": torch.zeros(8, 64), "policy.bias": torch.zeros(8),
                         "value.weight": torch.zeros(1, 64), "value.bias": torch.zeros(1)})
    bomb = st_save(bomb_tensors, metadata={MANIFEST_KEY: json.dumps({**manifest, "architecture": spec})})
    files = {
        "deep2000": (with_training("[" * 2000 + "]" * 2000), "nests deeper than"),
        "deepest": (with_training("[" * (max_manifest_chars // 2) + "]" * (max_manifest_chars // 2)),
                    "nests deeper than|over the"),
        "bomb": (bomb, "operations per observation"),
        "surrogate": (with_training('{"note": "\\ud800"}'), "invalid Unicode"),
        "secret": (SECRET, "over the"),
    }
    out = {}
    for name, (data, reason) in files.items():
        path = directory / f"{name}.safetensors"
        path.write_bytes(data)
        out[name] = (path, reason)
    return out


@pytest.mark.timing
@pytest.mark.ros
def test_hostile_bundles_on_topics_and_parameters_leave_the_graph_running(graph, bundles, tmp_path):
    import rclpy
    from rclpy.parameter_client import AsyncParameterClient

    hostile = _hostile(tmp_path)
    executor, sim, agents = graph(bundles["a"], 0, **SCENARIO)
    attacker = rclpy.create_node("attacker")
    executor.add_node(attacker)
    ns = contract.DEFAULT_NAMESPACE
    own = attacker.create_publisher(String, contract.policy_topic(ns, "agent_1"), contract.LATCHED_QOS)
    team = attacker.create_publisher(String, contract.team_policy_topic(ns), contract.LATCHED_QOS)
    assert spin_until(executor, lambda: len(sim.core.trace) >= 3, 30)

    for name, (path, _) in hostile.items():
        for pub in (own, team):
            before = agents[1].dropped_by["policy"]
            pub.publish(String(data=str(path)))
            assert spin_until(executor, lambda b=before: agents[1].dropped_by["policy"] > b, 60), name
            n = len(sim.core.trace)
            assert spin_until(executor, lambda n=n: len(sim.core.trace) >= n + 3, 60), name  # still answering
    assert all(a.slot.current.source == str(bundles["a"]) for a in agents)

    client = AsyncParameterClient(attacker, "/medc/medc_agent_0")
    assert spin_until(executor, lambda: client.services_are_ready(), 60)
    for name, (path, reason) in hostile.items():
        future = client.set_parameters([Parameter("policy", value=str(path))])
        assert spin_until(executor, future.done, 60)
        result = future.result().results[0]
        assert not result.successful, name
        assert __import__("re").search(reason, result.reason), (name, result.reason)
        assert "SECRET" not in result.reason and "\\x" not in result.reason
    n = len(sim.core.trace)
    assert spin_until(executor, lambda: len(sim.core.trace) >= n + 5, 30)
    assert sim.dropped == 0
    assert agents[0].slot.current.source == str(bundles["a"])


def _agent_process(policy: Path, log: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [str(BIN / "medc-agent"), "--ros-args", "-p", "agent_id:=agent_0", "-p", "agents:=3",
         "-p", f"policy:={policy}"],
        stdout=log.open("w"), stderr=subprocess.STDOUT, env=os.environ.copy(),
    )


@pytest.mark.timing
@pytest.mark.ros
def test_the_agent_process_survives_and_a_latched_bad_team_policy_does_not_stop_a_launch(
        rclpy_context, bundles, tmp_path):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter_client import AsyncParameterClient

    hostile = _hostile(tmp_path)
    node = rclpy.create_node("attacker")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    ns = contract.DEFAULT_NAMESPACE
    own = node.create_publisher(String, contract.policy_topic(ns, "agent_0"), contract.LATCHED_QOS)
    team = node.create_publisher(String, contract.team_policy_topic(ns), contract.LATCHED_QOS)
    procs = []

    def refusals(log: Path, name: str) -> int:
        """How many times the agent logging to ``log`` refused the hostile file ``name``."""
        return log.read_text().count(f"{name}.safetensors' refused, keeping the running one")

    def spin_alive(proc, log: Path, until) -> bool:
        """Spin until ``until()`` (120 s at most), asserting that the agent process stays alive."""
        deadline = time.monotonic() + 120
        while not until():
            assert proc.poll() is None, log.read_text()[-3000:]
            if time.monotonic() > deadline:
                return False
            executor.spin_once(timeout_sec=0.1)
        return True

    try:
        log1, log2 = tmp_path / "agent1.log", tmp_path / "agent2.log"
        first = _agent_process(bundles["a"], log1)
        procs.append(first)
        client = AsyncParameterClient(node, "/medc/medc_agent_0")  # medc-agent: medc_<agent_id> in /medc
        assert spin_until(executor, lambda: client.services_are_ready(), 120)
        # Latched, depth 1: each file once the agent heard the one before (own topic and team topic).
        assert spin_alive(first, log1, lambda: own.get_subscription_count() and team.get_subscription_count())
        for name in ("deep2000", "deepest", "bomb"):
            own.publish(String(data=str(hostile[name][0])))
            team.publish(String(data=str(hostile[name][0])))
            assert spin_alive(first, log1, lambda n=name: refusals(log1, n) >= 2), name

        def policy_of_the_running_agent() -> str:
            future = client.get_parameters(["policy"])  # the client of the moment (rebound below)
            assert spin_until(executor, future.done, 60)
            return future.result().values[0].string_value
        assert policy_of_the_running_agent() == str(bundles["a"])  # it keeps answering
        first.terminate()
        first.wait(30)
        # Its node gone from the graph, so that the services found next are the new agent's.
        gone = lambda: ("medc_agent_0", "/medc") not in node.get_node_names_and_namespaces()  # noqa: E731
        assert spin_until(executor, gone, 120)

        # The bomb is still latched on both topics: a new agent starts, refuses it and runs anyway.
        second = _agent_process(bundles["a"], log2)
        procs.append(second)
        client = AsyncParameterClient(node, "/medc/medc_agent_0")
        assert spin_until(executor, lambda: client.services_are_ready(), 120)
        assert spin_alive(second, log2, lambda: refusals(log2, "bomb") >= 2), log2.read_text()[-3000:]
        assert policy_of_the_running_agent() == str(bundles["a"])
        assert second.poll() is None, log2.read_text()[-3000:]
        log = log1.read_text() + log2.read_text()
        assert "nests deeper than" in log and "operations per observation" in log
        assert "Traceback" not in log
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
        node.destroy_node()


class _FakeRegistry:
    """Serves fixed bytes for any CID (the content hash is the content store's business)."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files

    def fetch(self, cid: str) -> bytes:
        return self.files[cid]


@pytest.mark.timing
@pytest.mark.ros
def test_the_bridge_vets_like_the_agent_and_keeps_serving(rclpy_context, bundles, tmp_path):
    import rclpy
    from medc_agents.policy_slot import PolicyRejected, load_policy
    from medc_interfaces.srv import FetchBundle
    from medc_registry.bridge_node import BridgeError, RegistryBridge, bridge_node_class
    from rclpy.executors import SingleThreadedExecutor

    hostile = _hostile(tmp_path)
    files = {name: path.read_bytes() for name, (path, _) in hostile.items()}
    files["good"] = bundles["a"].read_bytes()
    cache = tmp_path / "cache"
    bridge = RegistryBridge(_FakeRegistry(files), cache)
    for name, (path, reason) in hostile.items():
        with pytest.raises(BridgeError, match=reason) as at_bridge:
            bridge.fetch(name)
        with pytest.raises(PolicyRejected, match=reason) as at_agent:
            load_policy(str(path), (5, 10, 10), 8)
        # One vetting function: the same reason, after the source's name.
        assert str(at_bridge.value).split(": ", 1)[1].split(": ", 1)[1] == \
            str(at_agent.value).split(" is invalid: ", 1)[1].split(": ", 1)[1]
        assert "SECRET" not in str(at_bridge.value)
    assert sorted(p.name for p in cache.iterdir()) == []  # nothing refused was cached
    assert bridge.fetch("good")[0].is_file()

    node = bridge_node_class()(registry=_FakeRegistry(files), parameter_overrides=[
        Parameter("cache_dir", value=str(tmp_path / "node-cache"))])
    client_node = rclpy.create_node("operator")
    executor = SingleThreadedExecutor()
    for n in (node, client_node):
        executor.add_node(n)
    client = client_node.create_client(FetchBundle, f"{contract.DEFAULT_NAMESPACE}/registry/fetch_bundle")
    assert spin_until(executor, client.service_is_ready, 60)
    try:
        for cid in [*hostile, "missing-cid", "good"]:
            future = client.call_async(FetchBundle.Request(cid=cid, agent_ids=["agent_0"]))
            assert spin_until(executor, future.done, 60), cid
            res = future.result()
            assert res.ok == (cid == "good"), (cid, res.message)
            if cid in hostile:
                assert __import__("re").search(hostile[cid][1], res.message), res.message
            if cid == "missing-cid":  # a KeyError from the store: reported, not raised
                assert res.message == "internal error (KeyError)"
    finally:
        node.destroy_node()
        client_node.destroy_node()
