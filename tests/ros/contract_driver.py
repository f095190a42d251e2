"""A small UAV-team driver written from docs/ros-reference.md and the .msg files only (no medc_sim, no
medc_training): its own world, walls and sensor model, in ENU coordinates (REP 103).

It plays the part a real team's drivers (with a small coordinator) play: publishes the walls map,
every UAV's pose and radiation reading and one EpisodeStatus per team step (with its own session
id); waits for every agent's AgentMove, executes each (agent, episode, step) once (a re-sent move
from the same sender is ignored, the same agent from another sender is a duplicate, logged) and
goes on; an agent with no move ``--move-timeout-s`` after the step's first move (5 times as long
for one that has never moved) stays and is not waited for until a move from it is received again,
for the step being collected or the step just applied (docs/ros-reference.md, "A lost UAV", "Moves are
executed once"). A step not answered within ``--resend-s`` is published again (same stamp), well
before an agent would report a stall or take a teammate out: a best-effort pose or reading lost on
a loaded machine is sent again, not reported.

The loop's order (docs/ros-reference.md, "The driver loop"): every message already received is processed
(:func:`drain`) before each decision: before publishing a step, before taking an agent out and
before flying a step's moves. With ``--end-on declaration`` (or ``either``) the team's
SourceDeclaration for the current episode ends it, so a declaration that came with the step's
moves ends the episode before they are flown. Used by tests/ros/test_contract_driver.py and
tests/ros/test_team_liveness.py:

    python contract_driver.py --out steps.jsonl --steps 12 --seed 1 [--misstamp-step 4]
        [--resend-always] [--lose-agent 2 --lose-at-step 3] [--episodes 1] [--summary s.json]
        [--processes 4] [--end-on source|declaration|either]

writes one JSON line per applied team step (with the number of times it was re-sent) and exits 0
after ``--steps`` steps (or ``--episodes`` episodes); ``--summary`` writes what it received
(moves, re-sends, duplicates, agents taken out and back, declarations, episodes).
"""

from __future__ import annotations

import argparse
import json
import math
import secrets
import sys
import time

import numpy as np

# docs/ros-reference.md, "Moves": action -> one-cell step (di, dj) in the grid frame (i east, j north).
MOVES = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1))
SOURCE_STRENGTH, ATTENUATION, BACKGROUND = 1000.0, 0.5, 1.0
#: An agent that has never moved (still starting) is taken out only after this many move timeouts.
STARTUP_FACTOR = 5.0


def rate(walls_ij: np.ndarray, source_ij: tuple[int, int], sensor_ij: np.ndarray) -> np.ndarray:
    """Noise-free readings (counts/s) at sensor cells [K,2] (i, j) for one source, exactly as
    docs/ros-reference.md "Sensor model" specifies (float32 arithmetic, environment rows r = H - 1 - j).

    walls_ij: bool [W,H] indexed [i, j]."""
    f32 = np.float32
    width, height = walls_ij.shape
    walls_rc = walls_ij.T[::-1]  # [row, col], row 0 = north
    src = np.array([height - 1 - source_ij[1], source_ij[0]], dtype=f32)  # (row, col)
    sen = np.stack([height - 1 - sensor_ij[:, 1], sensor_ij[:, 0]], axis=1).astype(f32)
    delta = sen - src  # [K,2]
    samples = height + width
    t = (np.arange(samples, dtype=f32) + f32(0.5)) / f32(samples)
    rows = np.rint(src[0] + delta[:, 0:1] * t).astype(np.int64)  # round half to even
    cols = np.rint(src[1] + delta[:, 1:2] * t).astype(np.int64)
    inside = walls_rc[rows, cols]  # [K,S]
    crossings = inside[:, 0].astype(np.int64) + (inside[:, 1:] & ~inside[:, :-1]).sum(1)
    dist2 = (delta * delta).sum(1, dtype=f32)
    return f32(SOURCE_STRENGTH) * np.power(f32(ATTENUATION), crossings.astype(f32)) / (f32(1) + dist2) \
        + f32(BACKGROUND)


def realistic_factor(walls_ij: np.ndarray, source_ij: tuple[int, int], sensor_ij: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The realistic preset's geometric factor (docs/ros-reference.md "Sensor model": the rate is
    S * factor + B) at sensor cells [K,2] (i, j) for one source: 1 / (1 + d^2), or 0 when the
    segment between the two cell centres runs through the interior of a wall cell (the unit square
    around its centre) for a positive length. Float64, by clipping the segment to each wall cell
    (Liang-Barsky); returns (factor [K], grazing [K]): grazing = the segment touches a wall cell
    in a single point (a corner) without running through any, where the model leaves it open.

    walls_ij: bool [W,H] indexed [i, j]."""
    src = np.asarray(source_ij, dtype=np.float64)
    sen = np.asarray(sensor_ij, dtype=np.float64)
    delta = src - sen  # [K,2]: the segment sen + t * delta, t in [0, 1]
    enter = np.zeros(len(sen))
    blocked = np.zeros(len(sen), dtype=bool)
    touched = np.zeros(len(sen), dtype=bool)
    for wall in np.argwhere(walls_ij):
        enter[:] = 0.0
        leave = np.ones(len(sen))
        for axis in (0, 1):
            lo, hi = wall[axis] - 0.5 - sen[:, axis], wall[axis] + 0.5 - sen[:, axis]
            d = delta[:, axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                a, b = lo / d, hi / d
            moving = d != 0
            # Not moving along this axis: inside the slab for every t, or for none.
            inside = (lo < 0) & (hi > 0)
            enter = np.where(moving, np.maximum(enter, np.minimum(a, b)), np.where(inside, enter, np.inf))
            leave = np.where(moving, np.minimum(leave, np.maximum(a, b)), leave)
        blocked |= enter < leave
        touched |= enter == leave  # exact: the divisions are correctly rounded
    near = 1.0 / (1.0 + (delta * delta).sum(1))
    return np.where(blocked, 0.0, near), touched & ~blocked


def make_world(seed: int, size: int, agents: int):
    """Walls (two straight segments), a source and the agents' start cells, all in (i, j)."""
    rng = np.random.default_rng(seed)
    walls = np.zeros((size, size), dtype=bool)  # [i, j]
    j0 = int(rng.integers(3, size - 3))
    walls[1:6, j0] = True  # an east-west wall
    i0 = int(rng.integers(8, size - 1))
    walls[i0, max(0, j0 - 6):j0 - 1] = True  # a north-south wall, not touching the first
    free = np.argwhere(~walls)
    picks = rng.choice(len(free), agents + 1, replace=False)
    source = tuple(int(v) for v in free[picks[0]])
    starts = [tuple(int(v) for v in free[p]) for p in picks[1:]]
    return walls, source, starts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--agents", type=int, default=3)
    ap.add_argument("--size", type=int, default=13)
    ap.add_argument("--max-steps", type=int, default=50)
    ap.add_argument("--resolution", type=float, default=2.0)
    ap.add_argument("--origin", type=float, nargs=2, default=(-13.0, 4.0))
    ap.add_argument("--resend-s", type=float, default=1.0,
                    help="a step not answered this long is published again (same stamp)")
    ap.add_argument("--misstamp-step", type=int, default=-1, help="this team step's first reading of "
                    "agent_1 is stamped 1 us after its pose")
    ap.add_argument("--misstamp-hold-s", type=float, default=6.0,
                    help="the mis-stamped step is published again (stamped right) only this long after: "
                    "three times an agent's stall_timeout_s (2 s), so that every agent reports the stall")
    ap.add_argument("--namespace", default="/medc")
    ap.add_argument("--move-timeout-s", type=float, default=10.0,
                    help="an agent with no move this long after the step's first move stays and is not "
                    "waited for until it moves again")
    ap.add_argument("--resend-always", action="store_true",
                    help="publish every step twice (a re-send: same stamp), as a driver on a lossy link may")
    ap.add_argument("--lose-agent", type=int, default=-1, help="this UAV is lost from --lose-at-step on: "
                    "its pose and reading stop")
    ap.add_argument("--lose-at-step", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=0, help="stop after this many episodes (0: --steps only)")
    ap.add_argument("--end-on", choices=("source", "declaration", "either"), default="source",
                    help="what ends an episode besides --max-steps: a UAV on the source, the team's "
                    "SourceDeclaration for the episode, or whichever comes first")
    ap.add_argument("--summary", default="")
    ap.add_argument("--settle-s", type=float, default=1.0, help="discovery settling, s")
    ap.add_argument("--processes", type=int, default=0,
                    help="agent processes that listen (default --agents; more when two claim one agent id): "
                    "the first step waits until every topic published here has this many readers and "
                    "the move topics together as many writers")
    args = ap.parse_args(argv)

    import rclpy
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PoseStamped
    from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading, SourceDeclaration
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )

    def qos(depth: int, latched: bool) -> QoSProfile:
        durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
        return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST, durability=durability)

    rclpy.init()
    node = rclpy.create_node("uav_driver")
    ns, n, size, res = args.namespace, args.agents, args.size, args.resolution
    ids = [f"agent_{k}" for k in range(n)]
    pose_pubs = [node.create_publisher(PoseStamped, f"{ns}/{a}/pose", qos_profile_sensor_data) for a in ids]
    read_pubs = [node.create_publisher(RadiationReading, f"{ns}/{a}/radiation", qos_profile_sensor_data)
                 for a in ids]
    map_pub = node.create_publisher(OccupancyGrid, f"{ns}/map", qos(1, True))
    status_pub = node.create_publisher(EpisodeStatus, f"{ns}/episode", qos(20, False))
    result_pub = node.create_publisher(EpisodeStatus, f"{ns}/episode_result", qos(1000, True))
    moves: dict[int, int] = {}
    # The current episode and step; the step being collected ("open") and the one collected before
    # it ("previous": a move for it is not executed, but one received from an agent taken out brings
    # it back).
    state = {"episode": 0, "step": 0, "open": (-1, -1), "previous": (-1, -1)}
    session = secrets.token_hex(8)  # this run's id, on every status
    # Moves are executed once per (agent, episode, step): the first one received; the sender of each.
    executed: dict[tuple[int, int, int], str] = {}
    received: dict[int, int] = {}  # this step's move messages per agent, re-sends included
    summary = {"moves_received": 0, "resends_ignored": 0, "duplicates": [], "episodes": [], "lost": [],
               "back": [], "declarations": []}
    silent: set[int] = set()  # agents taken out: not waited for (docs/ros-reference.md, "A lost UAV")
    known: set[int] = set()  # agents that have had a move executed
    handled = [0]  # messages processed (drain() stops when none is left)
    declared: list = []  # the current episode's SourceDeclaration, once received

    def back(k: int, episode: int, step: int) -> None:
        """A move from agent k was received: if it was taken out, it is back in the team."""
        if k in silent:
            silent.discard(k)
            summary["back"].append([state["episode"], state["step"], ids[k], episode, step])
            print(f"{ids[k]} moved again (its move for episode {episode} step {step}): back in the team",
                  flush=True)

    def on_move(k: int, msg) -> None:
        handled[0] += 1
        if msg.agent_id != ids[k] or not 0 <= msg.action < 8:
            return
        summary["moves_received"] += 1
        episode, step = int(msg.episode), int(msg.step)
        key = (k, episode, step)
        if key in executed:
            if executed[key] != msg.sender:
                summary["duplicates"].append([ids[k], key[1], key[2], executed[key], msg.sender])
                print(f"duplicate agent id: {ids[k]} answered episode {key[1]} step {key[2]} from senders "
                      f"{executed[key]} and {msg.sender}", flush=True)
                return
            summary["resends_ignored"] += 1  # a re-send: already executed (or collected)
            if (episode, step) == state["previous"]:
                back(k, episode, step)
            return
        if (episode, step) == state["previous"]:
            back(k, episode, step)  # a late answer for the step just applied: not executed
            return
        if (episode, step) != (state["episode"], state["step"]):
            return
        executed[key] = msg.sender
        received[k] = received.get(k, 0) + 1
        moves[k] = int(msg.action)
        known.add(k)
        back(k, episode, step)

    def on_declaration(msg) -> None:
        handled[0] += 1
        if args.end_on == "source":
            return
        if declared or int(msg.episode) != state["episode"] or int(msg.step) > state["step"] \
                or (msg.map_stamp.sec, msg.map_stamp.nanosec) != state["map_stamp"]:
            return  # another episode's (or map's), or a second one
        declared.append(msg)

    def drain() -> None:
        """Process every message already received (the moves and declarations waiting in the
        readers), so that no decision is taken on older news than has arrived."""
        idle = 0
        while idle < 3:  # a pass may serve something other than the topics counted here
            before = handled[0]
            rclpy.spin_once(node, timeout_sec=0.0)
            idle = idle + 1 if handled[0] == before else 0

    move_subs = [node.create_subscription(AgentMove, f"{ns}/{a}/move", lambda m, k=k: on_move(k, m),
                                          qos(20, False)) for k, a in enumerate(ids)]
    declaration_sub = node.create_subscription(SourceDeclaration, f"{ns}/team/source_declared",
                                               on_declaration, qos(20, False))

    # Discovery (docs/ros-reference.md, "How one team step goes"): before the first step every
    # agent listens to every topic published here and publishes its move, or the first messages
    # are lost (and re-sent after resend_s).
    processes = args.processes or n
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and (
            any(p.get_subscription_count() < processes for p in (status_pub, *pose_pubs, *read_pubs))
            or any(s.get_publisher_count() < 1 for s in move_subs)
            or sum(s.get_publisher_count() for s in move_subs) < processes
            # Ending on the declaration: every agent's declaration writer is matched (a volatile
            # message sent before would never come).
            or (args.end_on != "source" and declaration_sub.get_publisher_count() < n)):
        rclpy.spin_once(node, timeout_sec=0.05)
    # A best-effort reader may match a moment after the writer sees it: let discovery settle.
    settle = time.monotonic() + args.settle_s
    while time.monotonic() < settle:
        rclpy.spin_once(node, timeout_sec=0.05)

    ox, oy = args.origin
    log = open(args.out, "w")  # noqa: SIM115 (closed in the finally below)
    world_seed = args.seed * 1000
    walls, source, cells = make_world(world_seed, size, n)
    done_steps = 0

    def now():
        return node.get_clock().now().to_msg()

    def publish_map():
        grid = OccupancyGrid()
        grid.header.stamp = grid.info.map_load_time = now()
        grid.header.frame_id = "map"
        grid.info.resolution = res
        grid.info.width = grid.info.height = size
        grid.info.origin.position.x, grid.info.origin.position.y = ox, oy
        grid.info.origin.orientation.w = 1.0
        # data[j * width + i], row j = 0 at the origin (the southern row).
        grid.data = [100 if walls[i, j] else 0 for j in range(size) for i in range(size)]
        map_pub.publish(grid)
        return grid.info.map_load_time

    def publish_state(stamp, map_stamp, misstamp: bool):
        values = rate(walls, source, np.array(cells))
        for k in range(n):
            if k == args.lose_agent and done_steps >= args.lose_at_step:
                continue  # the lost UAV: nothing comes from it any more
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = stamp, "map"
            i, j = cells[k]
            # ENU, off the cell centre, at 10 m altitude, with some heading: all allowed.
            pose.pose.position.x = ox + (i + 0.3) * res
            pose.pose.position.y = oy + (j + 0.6) * res
            pose.pose.position.z = 10.0
            yaw = 0.7 * k
            pose.pose.orientation.z, pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            pose_pubs[k].publish(pose)
            reading = RadiationReading()
            reading.header.stamp, reading.header.frame_id = stamp, "map"
            if misstamp and k == 1:
                # The mistake: 1 us off its pose.
                sec, nanosec = divmod(stamp.sec * 1_000_000_000 + stamp.nanosec + 1000, 1_000_000_000)
                reading.header.stamp = Time(sec=sec, nanosec=nanosec)
            reading.agent_id = ids[k]
            reading.value, reading.variance = float(values[k]), 0.0
            read_pubs[k].publish(reading)
        status = EpisodeStatus()
        status.header.stamp, status.header.frame_id = stamp, "map"
        status.episode, status.step, status.map_stamp = state["episode"], state["step"], map_stamp
        status.agent_ids = ids
        status.session = session
        status_pub.publish(status)
        return values

    def close_episode(success: bool, truncated: bool) -> None:
        """Publish the closing EpisodeStatus of the current episode (``state["step"]`` moves
        applied), and start the next episode on a new world and map."""
        nonlocal walls, source, cells, episode_walls, map_stamp, world_seed
        status = EpisodeStatus()
        status.header.stamp, status.header.frame_id = now(), "map"
        status.episode, status.step, status.map_stamp = state["episode"], state["step"], map_stamp
        status.agent_ids = ids
        status.done, status.success, status.truncated = True, success, truncated
        status.episode_length = state["step"]
        status.session = session
        status_pub.publish(status)
        summary["episodes"].append({"episode": state["episode"], "success": success, "length": state["step"],
                                    "declared": bool(declared)})
        result_pub.publish(status)
        state["episode"] += 1
        state["step"] = 0
        declared.clear()
        world_seed += 1
        walls, source, cells = make_world(world_seed, size, n)
        episode_walls = walls
        map_stamp = publish_map()
        state["map_stamp"] = (map_stamp.sec, map_stamp.nanosec)

    def end_on_declaration() -> bool:
        """The current episode ends on the team's declaration received for it (success: the
        declared cell is the source's cell; its length: the moves applied)."""
        if not declared:
            return False
        d = declared[0]
        right = (int(d.cell_i), int(d.cell_j)) == tuple(source)
        summary["declarations"].append({"episode": state["episode"], "step": int(d.step),
                                        "length": state["step"], "right": right, "mass": float(d.mass)})
        print(f"episode {state['episode']} ended by the team's declaration of step {d.step} after "
              f"{state['step']} moves: {'right' if right else 'wrong'} cell", flush=True)
        close_episode(right, False)
        return True

    map_stamp = publish_map()
    state["map_stamp"] = (map_stamp.sec, map_stamp.nanosec)
    episode_walls = walls
    try:
        while done_steps < args.steps and not (args.episodes and len(summary["episodes"]) >= args.episodes):
            # The driver loop's order: first every message already received (a declaration that came
            # after the last step was flown ends the episode before another step is published).
            drain()
            if end_on_declaration():
                continue
            stamp = now()
            moves.clear()
            received.clear()
            # A new step: the one collected before it becomes the previous step.
            state["previous"], state["open"] = state["open"], (state["episode"], state["step"])
            if args.lose_agent >= 0 and done_steps >= args.lose_at_step:
                silent.add(args.lose_agent)  # the driver knows its UAV is down: no move expected
            misstamp = done_steps == args.misstamp_step
            values = publish_state(stamp, map_stamp, misstamp)
            if args.resend_always:
                values = publish_state(stamp, map_stamp, False)
            sent = time.monotonic()
            wait_s = args.misstamp_hold_s if misstamp else args.resend_s  # before the next re-send
            resends = 0
            first = None  # when the step's first move came
            while len(moves) < n:
                rclpy.spin_once(node, timeout_sec=0.02)
                drain()  # take no agent out while a move from it waits to be processed
                if declared:
                    break  # the episode ends on the declaration: its moves are not flown
                waiting = [k for k in range(n) if k not in moves]
                if moves and all(k in silent for k in waiting):
                    break  # every agent still in the team has moved
                if moves and first is None:
                    first = time.monotonic()
                waited = time.monotonic() - first if first is not None else 0.0
                if first is not None and waited > args.move_timeout_s:
                    # They stay; not waited for until a move from them is received again. One that
                    # has never moved may still be starting: it is given STARTUP_FACTOR times as long.
                    newly = [k for k in waiting if k not in silent
                             and (k in known or waited > STARTUP_FACTOR * args.move_timeout_s)]
                    if newly:
                        silent.update(newly)
                        summary["lost"].append([state["episode"], state["step"], [ids[k] for k in newly]])
                        print(f"{', '.join(ids[k] for k in newly)} lost: no move within "
                              f"{args.move_timeout_s:g} s; staying in place", flush=True)
                    if all(k in silent for k in waiting):
                        break
                if time.monotonic() - sent > wait_s:  # re-send the step, same stamp
                    values = publish_state(stamp, map_stamp, False)
                    sent, wait_s = time.monotonic(), args.resend_s
                    resends += 1
            # Every message already received before the moves are flown: a declaration for this
            # step (sent before its publisher's move) ends the episode with these moves not flown.
            drain()
            if end_on_declaration():
                continue
            actions = [moves.get(k) for k in range(n)]
            before = list(cells)
            valid = []
            for k, a in enumerate(actions):
                if a is None:  # no move: the UAV stays
                    valid.append(True)
                    continue
                i, j = cells[k][0] + MOVES[a][0], cells[k][1] + MOVES[a][1]
                ok = 0 <= i < size and 0 <= j < size and not walls[i, j]
                valid.append(ok)
                if ok:
                    cells[k] = (i, j)
            log.write(json.dumps({
                "episode": state["episode"], "step": state["step"], "actions": actions, "valid": valid,
                "readings": [float(v) for v in values], "walls": episode_walls.astype(int).tolist(),
                "source": source, "cells": before, "received": [received.get(k, 0) for k in range(n)],
                "resends": resends,
            }) + "\n")
            log.flush()
            done_steps += 1
            state["step"] += 1
            found = args.end_on != "declaration" and any(c == source for c in cells)
            if found or state["step"] >= args.max_steps:
                close_episode(found, not found)
        # Let reliable messages go out before the process ends.
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        log.close()
        if args.summary:
            with open(args.summary, "w") as f:
                json.dump(summary, f)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
