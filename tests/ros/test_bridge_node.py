"""The registry bridge node against the embedded registry: request, fetch + verify, hand to an
agent, review; bad requests are answered with a reason and the node keeps serving."""

from __future__ import annotations

import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from medc_common import contract
from ros_helpers import spin_until
from std_msgs.msg import String

SCENARIO = {"agents": 3, "walls": 1, "grid": 10, "max_steps": 30, "seed": 8}


@pytest.fixture
def registry(tmp_path, bundles):
    from medc_registry import Registry

    reg = Registry.embedded(str(tmp_path / "store"))
    owner, user = reg.as_user(1), reg.as_user(2)
    owner.register_user()
    user.register_user()
    env = {"agents": 3, "walls": 1}
    good = owner.share_model(bundles["north"].read_bytes(), "target_localization", env, price=10**15)
    bad = owner.share_model(
        b"not a bundle at all", "target_localization", {"agents": 1, "walls": 3}, price=10**15
    )
    return user, good, bad


@pytest.mark.timing
@pytest.mark.ros
def test_bridge_request_fetch_handover_review(graph, bundles, registry, tmp_path):
    import rclpy
    from medc_interfaces.srv import FetchBundle, RequestExperts, SubmitReview
    from medc_registry.bridge_node import bridge_node_class

    user, good, bad = registry
    executor, sim, agents = graph(bundles["a"], 0, **SCENARIO)
    bridge = bridge_node_class()(
        registry=user,
        parameter_overrides=[rclpy.parameter.Parameter("cache_dir", value=str(tmp_path / "cache"))],
    )
    client_node = rclpy.create_node("operator")
    for node in (bridge, client_node):
        executor.add_node(node)
    ns = contract.DEFAULT_NAMESPACE
    # The bridge's heartbeat: (when the bridge published it, its stamp in s of ROS time; values).
    beats: list[tuple[float, dict]] = []
    client_node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: beats.extend(
        (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, {kv.key: kv.value for kv in st.values})
        for st in m.status if st.name == "medc_bridge" and st.hardware_id == "registry"),
        contract.DIAGNOSTICS_QOS)

    def call(srv_type, name, **fields):
        client = client_node.create_client(srv_type, f"{ns}/registry/{name}")
        assert spin_until(executor, client.service_is_ready, 60)
        future = client.call_async(srv_type.Request(**fields))
        assert spin_until(executor, future.done, 60)
        return future.result()

    try:
        res = call(
            RequestExperts,
            "request_experts",
            application="target_localization",
            requirements_json='{"agents": 3, "walls": 1}',
            count=1,
        )
        assert res.ok, res.message
        assert list(res.cids) == [good.cid] and int(res.price_wei) == 10**15

        # Bad requests get a reason; the node keeps serving.
        res_bad = call(
            RequestExperts,
            "request_experts",
            application="target_localization",
            requirements_json="[3, 1",
            count=1,
        )
        assert not res_bad.ok and "JSON" in res_bad.message
        # JSON nested 70,000 deep is refused by the bounded reader before any parser recursion,
        # in requirements and in weights alike; the node keeps serving.
        deep = "[" * 70_000 + "]" * 70_000
        for field in ("requirements_json", "weights_json"):
            given = {"requirements_json": '{"agents": 3, "walls": 1}', field: deep}
            res_deep = call(RequestExperts, "request_experts", application="target_localization",
                            count=1, **given)
            assert not res_deep.ok and "character limit" in res_deep.message, res_deep.message
        res_deep = call(RequestExperts, "request_experts", application="target_localization",
                        count=1, requirements_json="[" * 2000 + "]" * 2000)
        assert not res_deep.ok and "nests deeper than 16 levels" in res_deep.message, res_deep.message
        # A fault from outside that no layer typed (a chain node's broken HTTP answer, a dead socket)
        # is answered as an internal error; the node keeps serving.
        import http.client

        def broken(*args, **kwargs):
            raise http.client.HTTPException("got more than 100 headers")

        real_request, real_review = bridge.bridge.request, bridge.bridge.review
        bridge.bridge.request, bridge.bridge.review = broken, broken
        try:
            hurt = call(RequestExperts, "request_experts", application="target_localization",
                        requirements_json='{"agents": 3, "walls": 1}', count=1)
            assert not hurt.ok and hurt.message == "internal error (HTTPException)", hurt.message
            assert not call(SubmitReview, "submit_review", cid=good.cid, score=0.9).ok
        finally:
            bridge.bridge.request, bridge.bridge.review = real_request, real_review
        unknown = call(FetchBundle, "fetch_bundle", cid="QmYwAPJzv5CZsnA625s3Xf2nemtYgPpHdWEz79ojWnPbdG")
        assert not unknown.ok
        junk = call(FetchBundle, "fetch_bundle", cid=bad.cid, agent_ids=["agent_1"])
        assert not junk.ok and "not a valid policy bundle" in junk.message
        assert not call(FetchBundle, "fetch_bundle", cid="../../etc/passwd").ok
        assert not call(FetchBundle, "fetch_bundle", cid=good.cid, agent_ids=["robot_7"]).ok

        # Fetch + verify + hand to agent_0: it swaps to the verified file.
        fetched = call(FetchBundle, "fetch_bundle", cid=good.cid, agent_ids=["agent_0"])
        assert fetched.ok, fetched.message
        assert fetched.path.endswith(f"{good.cid}.safetensors")
        assert spin_until(executor, lambda: agents[0].slot.current.source == fetched.path, 60)
        assert agents[1].slot.current.source == str(bundles["a"])  # the junk never reached agent_1

        # An agent given a CID on its policy topic asks the bridge itself.
        pub = client_node.create_publisher(String, contract.policy_topic(ns, "agent_2"), contract.LATCHED_QOS)
        pub.publish(String(data=f"ipfs://{good.cid}"))
        assert spin_until(executor, lambda: agents[2].slot.current.source == fetched.path, 60)

        review = call(SubmitReview, "submit_review", cid=good.cid, score=0.9)
        assert review.ok, review.message
        assert review.tx_hash
        assert user.allocation(res.allocation_ids[0])[2] is True  # reviewed on chain
        again = call(SubmitReview, "submit_review", allocation_id=res.allocation_ids[0], score=0.5)
        assert not again.ok  # one review per allocation
        assert not call(SubmitReview, "submit_review", cid=good.cid, score=1.5).ok

        n = len(sim.core.trace)
        assert spin_until(executor, lambda: len(sim.core.trace) >= n + 5, 60)  # the team keeps playing

        # A heartbeat every second, with what the bridge served and refused; timed by the bridge's
        # own stamps. The executor calls a late timer once, never twice to catch up, so six beats
        # span at least 4 s however late some come (a 2 Hz heartbeat: 2.5 s).
        t0 = time.time()
        assert spin_until(executor, lambda: len([t for t, _ in beats if t >= t0]) >= 6, 60)
        stamps = [t for t, _ in beats if t >= t0][:6]
        assert stamps[-1] - stamps[0] >= 3.0, stamps
        last = beats[-1][1]
        assert {k: last[k] for k in ("request_experts", "fetch_bundle", "submit_review", "allocations",
                                     "bundles_cached")} == {"request_experts": "1", "fetch_bundle": "2",
                                                            "submit_review": "1", "allocations": "1",
                                                            "bundles_cached": "1"}, last
        assert (last["request_experts_refused"], last["fetch_bundle_refused"],
                last["submit_review_refused"]) == ("5", "4", "3"), last  # the internal errors counted too
        assert last["cache_dir"] == str(tmp_path / "cache")
    finally:
        executor.remove_node(bridge)
        executor.remove_node(client_node)
        bridge.destroy_node()
        client_node.destroy_node()
