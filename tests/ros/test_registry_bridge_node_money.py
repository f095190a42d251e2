"""The registry bridge node's money and text parameters over ROS: request_experts takes a price limit
per expert and the node a budget; a call over the budget or with a malformed limit is refused with
a reason and pays nothing; ``-p users_manager:=0x…`` (which ROS's parser reads as a float) is read
as the address written, and the same value from a params file is refused with a clear message."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from medc_common import contract
from ros_helpers import spin_until

ETH = 10**18
PRICE = 10**15
APP = "target_localization"
ADDRESS = "0x5FbDB2315678afecb367f032d93F642f64180aa3"


@pytest.mark.timing
@pytest.mark.ros
def test_request_experts_takes_a_price_limit_and_the_node_a_budget(rclpy_context, tmp_path):
    import rclpy
    from medc_interfaces.srv import RequestExperts
    from medc_registry import Registry
    from medc_registry.bridge_node import bridge_node_class, bridge_summary
    from rclpy.executors import SingleThreadedExecutor

    reg = Registry.embedded(str(tmp_path / "store"))
    griefer, honest, user = reg.as_user(1), reg.as_user(2), reg.as_user(3)
    for u in (griefer, honest, user):
        u.register_user()
    env = {"agents": 3, "walls": 2}
    griefer.share_model(b"dear", APP, env, 1000 * ETH)
    cheap = honest.share_model(b"cheap", APP, env, PRICE)
    bridge = bridge_node_class()(registry=user, parameter_overrides=[
        rclpy.parameter.Parameter("cache_dir", value=str(tmp_path / "cache")),
        rclpy.parameter.Parameter("budget", value="0.0015")])
    client_node = rclpy.create_node("operator")
    executor = SingleThreadedExecutor()
    for node in (bridge, client_node):
        executor.add_node(node)
    client = client_node.create_client(RequestExperts,
                                       f"{contract.DEFAULT_NAMESPACE}/registry/request_experts")

    def call(**fields):
        assert spin_until(executor, client.service_is_ready, 60)
        future = client.call_async(RequestExperts.Request(
            application=APP, requirements_json='{"agents": 3, "walls": 2}', count=1, **fields))
        assert spin_until(executor, future.done, 60)
        return future.result()

    try:
        res = call()  # the default limit: 10 x 0.001 ETH; the 1,000 ETH exact match passed over
        assert res.ok and list(res.model_ids) == [cheap.model_id] and res.price_wei == str(PRICE), res.message
        res = call(max_price_wei=str(1000 * ETH))  # covers it, but over what is left of the budget
        assert not res.ok and "over this bridge's budget: 0.0005 ETH left of 0.0015 ETH" in res.message
        res = call(max_price_wei="1e21")
        assert not res.ok and "max_price_wei must be a whole number of wei" in res.message
        res = call()  # the cheap one again: 0.001 ETH, over the 0.0005 ETH left
        assert not res.ok and "over this bridge's budget" in res.message
        assert reg.owed(griefer.address) == 0 and reg.owed(honest.address) == PRICE
        summary = bridge_summary(bridge.bridge, bridge.served)
        assert (summary["budget_wei"], summary["spent_wei"]) == (str(15 * 10**14), str(PRICE))
        assert (summary["request_experts"], summary["request_experts_refused"]) == ("1", "3")
    finally:
        executor.remove_node(bridge)
        executor.remove_node(client_node)
        bridge.destroy_node()
        client_node.destroy_node()
        executor.shutdown()


@pytest.mark.ros
def test_an_address_given_with_dash_p_is_read_as_the_text_written(rclpy_context):
    import rclpy
    from medc_registry.bridge_node import _declare_parameters

    command_line = ["medc-bridge", "--ros-args", "-p", f"users_manager:={ADDRESS}", "-p",
                    "medc_bridge:models_manager:=0x1234", "-p", "budget:=0.5", "-p", "content:=true"]
    node = rclpy.create_node("medc_bridge", cli_args=command_line[1:])
    try:
        # What ROS's parser made of them: a float, an int, a float, a bool.
        made = {name: type(p.value) for name, p in node._parameter_overrides.items()}
        assert made == {"users_manager": float, "models_manager": int, "budget": float, "content": bool}
        _names, connection, _cache, budget = _declare_parameters(node, command_line)
        assert connection["users_manager"] == ADDRESS and connection["models_manager"] == "0x1234"
        assert connection["content"] == "true" and budget == ETH // 2
    finally:
        node.destroy_node()


def _bridge(tmp_path, *ros_args: str) -> subprocess.CompletedProcess:
    keys = tmp_path / "keys.txt"
    keys.write_text("0x" + "11" * 32 + "\n")
    args = [sys.executable, "-m", "medc_registry.bridge_node", "--ros-args", "-p", "chain:=http://127.0.0.1:9",
            "-p", f"private_key_file:={keys}", "-p", f"content:={tmp_path / 'store'}", *ros_args]
    return subprocess.run(args, capture_output=True, text=True, timeout=180, env=dict(os.environ))


@pytest.mark.ros
def test_medc_bridge_reads_unquoted_addresses_and_refuses_them_clearly_from_a_params_file(tmp_path):
    """Unquoted on the command line, the addresses get the node as far as the chain (nothing
    answers on port 9: a clear refusal of the chain, no parameter type error). Unquoted in a
    params file, where the text is gone, the node says which parameter and how to quote it."""
    done = _bridge(tmp_path, "-p", f"users_manager:={ADDRESS}", "-p", f"models_manager:={ADDRESS}")
    assert done.returncode == 2, done.stderr
    assert "chain at http://127.0.0.1:9 is not reachable" in done.stderr and "Traceback" not in done.stderr
    params = tmp_path / "bridge.yaml"
    params.write_text(f"/**/medc_bridge:\n  ros__parameters:\n    users_manager: {ADDRESS}\n"
                      f"    models_manager: '{ADDRESS}'\n")
    done = _bridge(tmp_path, "--params-file", str(params))
    assert done.returncode == 2, done.stderr
    assert "parameter users_manager must be text" in done.stderr and "quote it" in done.stderr
    assert "Traceback" not in done.stderr
    done = _bridge(tmp_path, "-p", "budget:=plenty")
    assert done.returncode == 2 and "budget 'plenty' is not an amount" in done.stderr, done.stderr


def test_a_link_planted_in_the_bundle_cache_is_replaced_not_written_through(bundles, tmp_path):
    """The bridge stores a vetted bundle under <cache>/<cid>.safetensors through a fresh temporary
    file renamed into place: a link planted at that name is replaced, its target untouched, and no
    temporary file is left."""
    from medc_registry.bridge_node import RegistryBridge

    data = bundles["north"].read_bytes()

    class Store:
        def fetch(self, cid):
            return data

    cache = tmp_path / "cache"
    cache.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    cid = "QmYwAPJzv5CZsnA625s3Xf2nemtYgPpHdWEz79ojWnPbdG"
    (cache / f"{cid}.safetensors").symlink_to(victim)
    path, _manifest = RegistryBridge(Store(), cache).fetch(cid)
    assert victim.read_text() == "precious\n"
    assert not path.is_symlink() and path.read_bytes() == data
    assert sorted(p.name for p in cache.iterdir()) == [f"{cid}.safetensors"]
