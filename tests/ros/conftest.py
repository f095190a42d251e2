"""Fixtures of the ROS graph tests: an isolated DDS domain, rclpy, small test bundles."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from ros_domain import claim_domain

# A domain of our own (per test process, claimed with a lock: no other test process on this machine
# holds it, xdist worker or another session) so that no other graph talks to ours; set before rclpy
# or any child process starts.
os.environ["ROS_DOMAIN_ID"] = str(claim_domain())
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

GRID = 10
#: The environment a bundle trained in the benchmark's world with domain randomisation records
#: (besides its grid): the world and two of its options.
RADBENCH_DR = {"world": "radbench", "transmission_max": 0.3, "walls_min": 2}


def make_bundle(
    path: Path, seed: int, grid: int = GRID, favour: int | None = None, gain: float = 300.0,
    sensing: str | None = None, environment: dict | None = None,
) -> Path:
    """Save a lenet5 bundle with random weights whose greedy choice depends strongly on the input.

    ``favour``: the policy head ignores the input and always prefers that action.
    ``sensing``: the sensing preset its manifest records (environment.sensing; None: none, which
    means paper-simple). ``environment``: more keys of its manifest's environment.
    """
    import torch
    from medc_training.bundle import save_bundle
    from medc_training.nets import make_actor_critic

    torch.manual_seed(seed)
    net = make_actor_critic("lenet5", obs_shape=(5, grid, grid), num_actions=8)
    with torch.no_grad():
        for name, param in net.named_parameters():
            if name.startswith("policy"):
                param.mul_(gain)
        if favour is not None:
            net.policy.weight.zero_()
            net.policy.bias.zero_()
            net.policy.bias[favour] = 10.0
    env = {"grid": grid} if sensing is None else {"grid": grid, "sensing": sensing}
    env.update(environment or {})
    return save_bundle(path, net, {"application": "target_localization", "environment": env})


@pytest.fixture(scope="session")
def bundles(tmp_path_factory) -> dict[str, Path]:
    """Test bundles for a 10x10 grid: 'a', 'b' (different random nets), 'north' (always N), 'grid30',
    'realistic' (trained, says its manifest, under the realistic sensing preset), 'radbench' (trained,
    says its manifest, in the benchmark's world with domain randomisation)."""
    d = tmp_path_factory.mktemp("bundles")
    return {
        "a": make_bundle(d / "a.safetensors", 1),
        "b": make_bundle(d / "b.safetensors", 2),
        "north": make_bundle(d / "north.safetensors", 3, favour=0),
        "grid30": make_bundle(d / "grid30.safetensors", 4, grid=30),
        "realistic": make_bundle(d / "realistic.safetensors", 5, sensing="realistic"),
        "radbench": make_bundle(d / "radbench.safetensors", 6, environment=RADBENCH_DR),
    }


@pytest.fixture
def rclpy_context():
    """rclpy initialised for one test, shut down after it."""
    import rclpy

    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture
def graph(rclpy_context):
    """A factory of in-process graphs (sim + agents on one executor), all torn down after the test."""
    from medc_bringup.launcher import build_graph, load_config, resolve_policies
    from rclpy.executors import SingleThreadedExecutor

    made = []

    def make(policy: Path, episodes: int, shared_feed: bool = True, **scenario):
        cfg = load_config(None, policy=str(policy), **scenario)
        sim, agents, nodes = build_graph(
            cfg, resolve_policies(cfg), episodes, record=True, shared_feed=shared_feed
        )
        executor = SingleThreadedExecutor()
        for node in nodes:
            executor.add_node(node)
        made.append((executor, nodes))
        return executor, sim, agents

    yield make
    for executor, nodes in made:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
