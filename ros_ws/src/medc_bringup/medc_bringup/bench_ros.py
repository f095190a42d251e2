"""medc-bench ros: how fast the ROS graph decides, over real DDS (FastDDS via rclpy).

Measures, with the simulator in this process and the agent nodes either each in its own
``medc-agent`` process (the deployment a real team has) or all on the simulator's executor:

* team decision latency, p50/p99: the simulator publishes a step -> it has received every
  agent's move; for 3 and 10 agents;
* the highest stepped rate sustained for ``--duration`` seconds with 3 agents: stepped mode
  with no rate limit, team steps per second over the whole window.

Targets on the reference machine (2 CPU cores): p99 < 20 ms with 10 agents, >= 50 team
steps/s with 3 agents. The last line printed is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _bench_bundle(grid: int, folder: Path) -> Path:
    """A lenet5 bundle for the grid (random weights: the cost of a decision does not depend on them)."""
    import torch
    from medc_training.bundle import save_bundle
    from medc_training.envs.names import DEFAULT_APPLICATION
    from medc_training.envs.target_localization import ACTIONS
    from medc_training.envs.tl_observation import observation_shape
    from medc_training.nets import make_actor_critic

    torch.manual_seed(0)
    # The paper's five maps (a bundle without an observation name takes them).
    shape = observation_shape("maps", grid)
    net = make_actor_critic("lenet5", obs_shape=shape, num_actions=len(ACTIONS))
    return save_bundle(
        folder / f"bench_lenet5_{grid}.safetensors", net, {"application": DEFAULT_APPLICATION}
    )


def run_graph(
    agents: int,
    bundle: Path | str,
    *,
    in_process: bool = False,
    steps: int = 0,
    duration: float = 0.0,
    warmup: int = 20,
    grid: int = 30,
    walls: int = 2,
    seed: int = 0,
) -> dict:
    """Run the simulator here and ``agents`` agent nodes running ``bundle`` (a bundle path or a
    classical controller's name; own processes, or with ``in_process`` on the simulator's
    executor); stop after ``steps`` measured steps or ``duration`` seconds (after ``warmup``
    steps). Returns latencies and throughput."""
    from medc_common.executors import make_executor

    from medc_bringup.launcher import _stop, load_config, resolve_policies

    cfg = load_config(None, agents=agents, grid=grid, walls=walls, seed=seed, policy=str(bundle))
    resolve_policies(cfg)  # fills max_steps from the bundle and checks it fits the grid
    executor = make_executor()
    sim, nodes, children = _start_graph(cfg, agents, str(bundle), in_process)
    for node in nodes:
        executor.add_node(node)
    try:
        figures = _measure(sim, executor, steps, duration, warmup)
        return {"agents": agents, "deployment": "in-process" if in_process else "processes", **figures}
    finally:
        _stop(children)
        executor.shutdown()
        for node in nodes:
            node.destroy_node()


def _start_graph(cfg, agents: int, bundle: str, in_process: bool) -> tuple:
    """(simulator node, nodes to spin here, agent processes): the agents on this executor with
    ``in_process``, else each in its own ``medc-agent`` process."""
    import subprocess

    from medc_common.contract import agent_node_name
    from medc_sim.simulator import SimNode
    from rclpy.parameter import Parameter

    from medc_bringup.launcher import _child_env, agent_parameters, build_graph, ros_args, sim_parameters

    if in_process:
        sim, _, nodes = build_graph(cfg, [bundle] * agents)
        return sim, nodes, []
    sim = SimNode(namespace=cfg.namespace,
                  parameter_overrides=[Parameter(k, value=v) for k, v in sim_parameters(cfg).items()])
    bindir = Path(sys.executable).parent
    children = [
        subprocess.Popen(
            [str(bindir / "medc-agent"),
             *ros_args(agent_node_name(i), agent_parameters(cfg, i, bundle), cfg.namespace)],
            env=_child_env(),
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for i in range(agents)
    ]
    return sim, [sim], children


def _measure(sim, executor, steps: int, duration: float, warmup: int) -> dict:
    """Spin until the agents have answered ``warmup`` steps (120 s at most), then measure
    ``steps`` steps or ``duration`` seconds: the figures of :func:`run_graph`."""
    from medc_training.stats import percentile

    deadline = time.monotonic() + 120
    while len(sim.latencies) < warmup:
        executor.spin_once(timeout_sec=0.05)
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"the agents did not start answering within 120 s ({len(sim.latencies)} steps)"
            )
    sim.latencies.clear()
    resends = sim.resends
    start = time.perf_counter()
    while (steps and len(sim.latencies) < steps) or (duration and time.perf_counter() - start < duration):
        executor.spin_once(timeout_sec=0.05)
    elapsed = time.perf_counter() - start
    lat = list(sim.latencies)
    return {
        "steps": len(lat),
        "seconds": round(elapsed, 3),
        "team_steps_per_s": round(len(lat) / elapsed, 2),
        "latency_ms_p50": round(1000 * percentile(lat, 50), 3),
        "latency_ms_p99": round(1000 * percentile(lat, 99), 3),
        "latency_ms_mean": round(1000 * statistics.fmean(lat), 3),
        "resends": sim.resends - resends,
        "dropped": sim.dropped,
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``medc-bench ros``."""
    from medc_training.console import HelpFormatter
    from medc_training.controllers import CONTROLLERS

    parser = argparse.ArgumentParser(prog="medc-bench ros", description=__doc__.split("\n\n")[0],
                                     formatter_class=HelpFormatter)
    parser.add_argument("--steps", type=int, default=500, help="measured steps per latency run")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of the sustained-rate run")
    parser.add_argument("--policy", help="bundle to run, on its grid, or a classical controller ("
                        f"{', '.join(CONTROLLERS)}) on the 30x30 grid (default: a lenet5 for the 30x30 grid)")
    parser.add_argument("--quick", action="store_true", help="100 steps and 10 s (a smoke run)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.quick:
        args.steps, args.duration = 100, 10.0

    from medc_common.ros_env import require_interfaces

    require_interfaces()
    import rclpy

    # A domain of its own, unless the caller chose one: no cross-talk with a running graph.
    os.environ.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))
    import torch

    torch.set_num_threads(1)
    rclpy.init(args=["medc-bench-ros"])
    results: dict = {
        "benchmark": "ros",
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "transport": "FastDDS (rclpy, EventsExecutor)",
    }
    try:
        with tempfile.TemporaryDirectory() as tmp:
            grid, bundle = _policy(args.policy, CONTROLLERS, Path(tmp))
            results["policy"] = str(args.policy or "lenet5 (random weights)")
            results["grid"] = grid
            results.update(_runs(bundle, grid, args.steps, args.duration))
    finally:
        rclpy.try_shutdown()
    results.update(_targets(results))
    load = os.getloadavg()
    # The machine is shared; the figures are only comparable at a similar load.
    results["load_average_1_5_15"] = [round(x, 2) for x in load]
    print(json.dumps(results))
    return 0


def _policy(policy: str | None, controllers, tmp: Path) -> tuple[int, Path | str]:
    """(grid, what the agents run) for ``--policy``: a controller on the 30x30 grid, a bundle on its
    grid, or (none given) a random-weight lenet5 written under ``tmp``."""
    if policy and policy.strip() in controllers:
        return 30, policy.strip()
    if policy:
        from medc_training.bundle import read_manifest

        return int(read_manifest(Path(policy))["observation"]["height"]), Path(policy)
    return 30, _bench_bundle(30, tmp)


def _runs(bundle: Path | str, grid: int, steps: int, duration: float) -> dict:
    """The latency runs (3 and 10 agents) and the sustained-rate run (3 agents), in processes and
    in-process, each printed as it ends."""
    results = {}
    for in_process in (False, True):
        where = "in-process" if in_process else "processes"
        for n in (3, 10):
            r = run_graph(n, bundle, in_process=in_process, steps=steps, grid=grid)
            print(
                f"latency, {n} agents, {where}: p50 {r['latency_ms_p50']} ms, "
                f"p99 {r['latency_ms_p99']} ms "
                f"over {r['steps']} steps ({r['team_steps_per_s']} team steps/s)",
                flush=True,
            )
            results[f"latency_{n}_agents_{where}"] = r
        r = run_graph(3, bundle, in_process=in_process, duration=duration, grid=grid)
        print(
            f"sustained stepped rate, 3 agents, {where}: {r['team_steps_per_s']} team steps/s over "
            f"{r['seconds']} s ({r['steps']} steps)",
            flush=True,
        )
        results[f"sustained_3_agents_{where}"] = r
    return results


def _targets(results: dict) -> dict:
    """The headline figures and whether each deployment meets the targets."""
    out = {}
    for where in ("processes", "in-process"):
        p99 = results[f"latency_10_agents_{where}"]["latency_ms_p99"]
        rate = results[f"sustained_3_agents_{where}"]["team_steps_per_s"]
        out[f"latency_p99_ms_10_agents_{where}"] = p99
        out[f"sustained_team_steps_per_s_3_agents_{where}"] = rate
        out[f"targets_met_{where}"] = {
            "p99_below_20ms_10_agents": p99 < 20.0,
            "at_least_50_steps_per_s_3_agents": rate >= 50.0,
        }
    return out


if __name__ == "__main__":
    sys.exit(main())
