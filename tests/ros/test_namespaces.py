"""Names are relative to the node's namespace: ``-r __ns:=/team3`` (or the launcher's namespace)
moves a whole team, its registry bridge and the agents' bridge service included; the default
graph keeps its fully-qualified names; the ``namespace`` parameter pins names as before and may not
contradict a remapped namespace; the shipped parameter files apply in any namespace."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from medc_common import contract
from ros_helpers import spin_until

SRC = Path(__file__).resolve().parents[2] / "ros_ws" / "src"


def test_contract_names_are_relative_for_nodes_and_qualified_for_tools():
    assert contract.pose_topic(contract.RELATIVE, "agent_0") == "agent_0/pose"
    assert contract.pose_topic("/medc", "agent_0") == "/medc/agent_0/pose"
    assert contract.estimate_topic("/team2/") == "/team2/team/source_estimate"
    assert contract.status_topic("/") == "/episode"
    assert contract.registry_service(None, "fetch_bundle") == "registry/fetch_bundle"
    assert contract.registry_service("/medc", "submit_review") == "/medc/registry/submit_review"
    with pytest.raises(ValueError, match="unknown registry service 'fetch'"):
        contract.registry_service(None, "fetch")
    assert contract.team_name(None, "registry/fetch_bundle") == "registry/fetch_bundle"
    assert contract.team_name("/gate", "registry/fetch_bundle") == "/gate/registry/fetch_bundle"
    assert contract.team_name("/gate", "/other/fetch") == "/other/fetch"
    assert contract.DIAGNOSTICS_TOPIC == "/diagnostics"  # global by ROS convention


def test_team_namespace_rules():
    assert contract.team_namespace("/medc") == ("/medc", None)
    assert contract.team_namespace("/team2", "") == ("/team2", None)
    assert contract.team_namespace("/team2", "team2/") == ("/team2", None)  # the same namespace
    assert contract.team_namespace("/medc", "/gate") == ("/gate", "/gate")  # pinned, as before
    with pytest.raises(ValueError, match="contradicts the node's namespace /team2"):
        contract.team_namespace("/team2", "/team3")
    with pytest.raises(ValueError, match=r"not a valid ROS namespace: .*alphanumerics"):
        contract.team_namespace("/medc", "team 2")
    assert contract.check_namespace("team2") == "/team2" and contract.check_namespace("/") == "/"
    with pytest.raises(ValueError, match="token that starts with a number"):
        contract.check_namespace("/2nd")


def test_launcher_puts_every_node_in_the_namespace(tmp_path, capsys):
    from medc_bringup.launcher import (
        agent_parameters,
        load_config,
        main,
        resolve_policies,
        ros_args,
        sim_parameters,
    )

    cfg = load_config(None, namespace="team2", policy="greedy")
    resolve_policies(cfg)
    assert cfg.namespace == "/team2"
    assert "namespace" not in sim_parameters(cfg) and "namespace" not in agent_parameters(cfg, 0, "greedy")
    assert ros_args("medc_sim", {"seed": 1}, cfg.namespace) == [
        "--ros-args", "-r", "__node:=medc_sim", "-r", "__ns:=/team2", "-p", "seed:=1"]
    config = tmp_path / "launch.yaml"
    config.write_text("namespace: /team-2\npolicy: greedy\n")
    with pytest.raises(ValueError, match="'/team-2' is not a valid ROS namespace"):
        load_config(config)
    assert main(["--policy", "greedy", "--namespace", "team 2", "--episodes", "1"]) == 2
    assert "not a valid ROS namespace" in capsys.readouterr().err


class _Store:
    """Serves one bundle's bytes for one content id (the content hash is the store's business)."""

    def __init__(self, cid: str, data: bytes) -> None:
        self.files = {cid: data}

    def fetch(self, cid: str) -> bytes:
        return self.files[cid]


@pytest.mark.timing
@pytest.mark.ros
def test_a_team_and_its_bridge_in_another_namespace(graph, bundles, tmp_path):
    """A launcher team in /team3 plays; its topics are under /team3 and none under /medc; an agent
    given a content id asks the bridge of its own namespace (the default, relative bridge_service),
    which hands the verified bundle back on /team3/agent_1/policy."""
    import rclpy
    from medc_registry.bridge_node import bridge_node_class
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    cid = "QmYwAPJzv5CZsnA625s3Xf2nemtYgPpHdWEz79ojWnPbdG"
    executor, sim, agents = graph(bundles["a"], 0, shared_feed=False, namespace="/team3", agents=2, walls=1,
                                  grid=10, max_steps=20, seed=4)
    bridge = bridge_node_class()(registry=_Store(cid, bundles["north"].read_bytes()), namespace="/team3",
                                 parameter_overrides=[Parameter("cache_dir", value=str(tmp_path / "cache"))])
    operator = rclpy.create_node("operator")
    try:
        for node in (bridge, operator):
            executor.add_node(node)
        assert {n.get_namespace() for n in (sim, *agents, bridge)} == {"/team3"}
        assert sim.pose_pubs[1].topic_name == "/team3/agent_1/pose"
        assert agents[0].move_pub.topic_name == "/team3/agent_0/move"
        assert agents[1].bridge_service == "registry/fetch_bundle"
        assert spin_until(executor, lambda: len(sim.core.trace) >= 5, 30)
        topics = {name for name, _ in operator.get_topic_names_and_types()}
        assert {"/team3/episode", "/team3/agent_1/radiation", "/team3/team/source_estimate"} <= topics
        assert not [t for t in topics if t.startswith("/medc/")], sorted(topics)
        services = {name for name, _ in operator.get_service_names_and_types()}
        assert {contract.registry_service("/team3", s) for s in contract.REGISTRY_SERVICES} <= services

        topic = contract.policy_topic("/team3", "agent_1")
        pub = operator.create_publisher(String, topic, contract.LATCHED_QOS)
        pub.publish(String(data=f"ipfs://{cid}"))
        fetched = str(tmp_path / "cache" / f"{cid}.safetensors")
        assert spin_until(executor, lambda: agents[1].slot.current.source == fetched, 60)
        assert agents[0].slot.current.source == str(bundles["a"])
        n = len(sim.core.trace)
        assert spin_until(executor, lambda: len(sim.core.trace) >= n + 5, 30)  # the team keeps playing
    finally:
        for node in (bridge, operator):
            executor.remove_node(node)
            node.destroy_node()


@pytest.mark.ros
def test_ns_remap_moves_a_node_and_the_parameter_pins_or_refuses(rclpy_context, bundles):
    from medc_agents.node import AgentNode
    from medc_sim.simulator import SimNode
    from rclpy.parameter import Parameter

    remap = ["--ros-args", "-r", "__ns:=/team4"]
    made = []
    try:
        sim = SimNode(cli_args=remap, parameter_overrides=[Parameter("agents", value=2)])
        made.append(sim)
        assert (sim.get_namespace(), sim.namespace_) == ("/team4", "/team4")
        assert [p.topic_name for p in sim.pose_pubs] == ["/team4/agent_0/pose", "/team4/agent_1/pose"]
        assert sim.results_pub.topic_name == "/team4/episode_result"
        default = SimNode(node_name="medc_sim_default")
        made.append(default)
        assert default.get_fully_qualified_name() == "/medc/medc_sim_default"
        assert default.status_pub.topic_name == "/medc/episode"  # the default graph's names, unchanged
        gate = Parameter("namespace", value="/gate")
        pinned = SimNode(node_name="medc_sim_pinned", parameter_overrides=[gate])
        made.append(pinned)
        assert pinned.map_pub.topic_name == "/gate/map" and pinned.namespace_ == "/gate"
        with pytest.raises(ValueError, match=r"namespace parameter '/team5' contradicts .* /team4"):
            SimNode(node_name="medc_sim_bad", cli_args=remap,
                    parameter_overrides=[Parameter("namespace", value="/team5")])

        policy = Parameter("policy", value=str(bundles["a"]))
        team = Parameter("agents", value=3)
        agent = AgentNode(agent_id="agent_0", cli_args=remap, parameter_overrides=[policy, team])
        made.append(agent)
        assert agent.move_pub.topic_name == "/team4/agent_0/move"
        assert agent.resolve_service_name(agent.bridge_service) == "/team4/registry/fetch_bundle"
        gated = AgentNode(agent_id="agent_1", parameter_overrides=[policy, team, gate])
        made.append(gated)
        assert gated.bridge_service == "/gate/registry/fetch_bundle"
        assert gated.move_pub.topic_name == "/gate/agent_1/move"
    finally:
        for node in made:
            node.destroy_node()


@pytest.mark.ros
def test_shipped_parameter_files_apply_in_any_namespace(rclpy_context, tmp_path):
    """sim.yaml and bridge.yaml name their node as /**/<name>: a node moved to /team2 still reads
    them (a key without the wildcard would match /<name> only)."""
    from medc_registry.bridge_node import bridge_node_class
    from medc_sim.simulator import SimNode

    def changed(package: str, name: str, key: str, value) -> str:
        data = yaml.safe_load((SRC / package / "config" / name).read_text())
        (node_key,) = data
        data[node_key]["ros__parameters"][key] = value
        out = tmp_path / name
        out.write_text(yaml.safe_dump(data))
        return str(out)

    sim = SimNode(namespace="/team2", cli_args=["--ros-args", "--params-file",
                                                 changed("medc_sim", "sim.yaml", "seed", 7)])
    cache = tmp_path / "bridge-cache"
    bridge = bridge_node_class()(registry=object(), namespace="/team2", cli_args=[
        "--ros-args", "--params-file", changed("medc_registry", "bridge.yaml", "cache_dir", str(cache))])
    try:
        assert sim.get_parameter("seed").value == 7 and sim.get_namespace() == "/team2"
        assert sim.namespace_ == "/team2" and sim.pose_pubs[0].topic_name == "/team2/agent_0/pose"
        assert bridge.get_parameter("cache_dir").value == str(cache)
    finally:
        sim.destroy_node()
        bridge.destroy_node()
