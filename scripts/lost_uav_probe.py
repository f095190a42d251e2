#!/usr/bin/env python
"""How a team does with 3, 2 and 1 of its agents left (docs/ros-reference.md, "A lost UAV").

    python scripts/lost_uav_probe.py --episodes 40 [--gone] [--policy models/team] [--seed 0]

Runs the launch config's scenario in one process (simulator and agent nodes on one executor) once
per number of agents left; the other agent nodes exist but never run, so the simulator takes them
out after ``move_timeout_s`` (0.5 s here) and their UAVs hover in place, still sensing. With
``--gone`` the lost UAVs publish no pose and no reading either (a lost link): the agents left take
them out after their ``lost_timeout_s``. The last line printed is JSON: per number left, the
episodes, how many found the source, the mean length.
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--gone", action="store_true",
                    help="lost UAVs publish nothing (else they hover and sense)")
    ap.add_argument("--policy", default=None, help="as medc-launch --policy (default: the launch config's)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(200 + os.getpid() % 30))  # away from other graphs

    import rclpy
    from medc_bringup.launcher import build_graph, load_config, resolve_policies
    from rclpy.executors import SingleThreadedExecutor

    rclpy.init()
    out = {}
    try:
        cfg = load_config(None, seed=args.seed, **({"policy": args.policy} if args.policy else {}))
        policies = resolve_policies(cfg)
        team = len(policies)
        for left in range(team, 0, -1):
            if args.gone and left == team:
                continue
            sim, agents, nodes = build_graph(cfg, policies, args.episodes, shared_feed=False)
            sim.move_timeout_s = 0.5
            if args.gone:  # the lost UAVs' drivers publish nothing any more
                for k in range(left, team):
                    sim.pose_pubs[k].publish = sim.reading_pubs[k].publish = lambda *_a, **_k: None
            executor = SingleThreadedExecutor()
            for node in (sim, *agents[:left]):
                executor.add_node(node)
            t0 = time.monotonic()
            while not sim.finished and time.monotonic() - t0 < 600:
                executor.spin_once(timeout_sec=0.05)
            results = sim.core.results
            found = sum(r.success for r in results)
            out[left] = {"episodes": len(results), "found": found,
                         "mean_length": round(sum(r.length for r in results) / max(1, len(results)), 3),
                         "wall_s": round(time.monotonic() - t0, 1)}
            executor.shutdown()
            for node in nodes:
                node.destroy_node()
            scenario = [sim.core.config.agents, sim.core.config.walls, sim.core.config.grid,
                        sim.core.config.max_steps]
    finally:
        rclpy.try_shutdown()
    print(json.dumps({"scenario": scenario, "seed": args.seed, "gone": args.gone, "left": out}))


if __name__ == "__main__":
    main()
