"""An intruder on a team's domain and namespace (tests/ros/test_authenticated_team.py): after each
status of the driver it forges statuses, declarations, moves, poses and readings, unsigned, signed
with another key, or replayed verbatim from the team's own signed traffic.

Run as a process (``python intruder.py --namespace /ns --lost agent_2 --wrong-key FILE``) it starts
three such intruders idle, prints ``CAPTURED`` once each holds genuine traffic to replay, forges
from SIGUSR1 on and stops on SIGINT: an attacker in a process of its own, as on a real domain.
"""

from __future__ import annotations

import copy
import time

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from medc_common import contract
from medc_common.auth_node import NodeAuth, message_digest
from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading, SourceDeclaration

IDS = contract.agent_ids(3)
#: One hour, in seconds: how far ahead the intruder stamps its poses and readings.
AHEAD_S = 3600
MODES = ("unsigned", "wrong key", "replay")


class Intruder:
    """A node on the team's namespace that forges every kind of team message after each status it
    hears: ``mode`` 'unsigned' (no auth), 'wrong key' (signed with another key) or 'replay'
    (re-publishes, unchanged, genuine signed messages it captured earlier)."""

    def __init__(self, node, namespace: str, mode: str, wrong_key_file=None, lost: str | None = None) -> None:
        self.node, self.ns, self.mode, self.lost = node, namespace, mode, lost
        self.signer = NodeAuth(str(wrong_key_file), "intruder") if wrong_key_file else None
        self.active = True
        #: Forge moves only (no statuses, declarations, poses, readings).
        self.only_moves = False
        #: Seconds between two bursts at least (0: one burst per status heard).
        self.min_period_s = 0.0
        self._last_burst = 0.0
        self.sent = 0
        ns = namespace
        self.pubs = {
            "status": node.create_publisher(EpisodeStatus, contract.status_topic(ns), contract.RELIABLE_QOS),
            "declaration": node.create_publisher(SourceDeclaration, contract.declaration_topic(ns),
                                                 contract.RELIABLE_QOS),
            **{f"move {a}": node.create_publisher(AgentMove, contract.move_topic(ns, a),
                                                  contract.RELIABLE_QOS) for a in IDS},
            **{f"pose {a}": node.create_publisher(PoseStamped, contract.pose_topic(ns, a),
                                                  contract.SENSOR_QOS) for a in IDS},
            **{f"reading {a}": node.create_publisher(RadiationReading, contract.radiation_topic(ns, a),
                                                     contract.SENSOR_QOS) for a in IDS},
        }
        #: Genuine signed messages heard, by publisher key (for the replay).
        self.captured: dict[str, list] = {}
        self.senders: dict[str, str] = {}
        self.heard: set[tuple] = set()
        node.create_subscription(EpisodeStatus, contract.status_topic(ns), self.on_status,
                                 contract.RELIABLE_QOS)
        for a in IDS:
            node.create_subscription(AgentMove, contract.move_topic(ns, a), self._capture(f"move {a}"),
                                     contract.RELIABLE_QOS)
            node.create_subscription(RadiationReading, contract.radiation_topic(ns, a),
                                     self._capture(f"reading {a}"), contract.SENSOR_QOS)
        node.create_subscription(SourceDeclaration, contract.declaration_topic(ns),
                                 self._capture("declaration"), contract.RELIABLE_QOS)

    def _capture(self, key: str):
        def take(msg) -> None:
            if key.startswith("move") and msg.sender not in ("ghost", "intruder"):
                self.senders.setdefault(msg.agent_id, msg.sender)  # the live agent's public id
            if msg.auth.sender and msg.auth.sender != "intruder":
                self.captured.setdefault(key, []).append(msg)
        return take

    def _send(self, key: str, msg, topic: str) -> None:
        if self.signer is not None:
            self.signer.sign(msg, topic)
        self.pubs[key].publish(msg)
        self.sent += 1

    def on_status(self, msg: EpisodeStatus) -> None:
        heard = (msg.auth.sender, msg.auth.counter, msg.episode, msg.step, msg.header.stamp.sec,
                 msg.header.stamp.nanosec)
        if not self.active or msg.auth.sender == "intruder" or msg.step >= 10**9 or heard in self.heard:
            return  # forged or replayed: not answered (intruders would feed each other)
        self.heard.add(heard)
        now = time.monotonic()
        if now - self._last_burst < self.min_period_s:
            return
        self._last_burst = now
        self.captured.setdefault("status", []).append(msg)
        if self.mode == "replay":
            self._replay()
        else:
            self._forge(msg)

    def _replay(self) -> None:
        # The oldest captured messages of every kind, verbatim: valid MACs, old counters.
        for key, msgs in self.captured.items():
            if msgs:
                self.pubs[key].publish(msgs[0])
                self.sent += 1

    def _forge(self, status: EpisodeStatus) -> None:
        ns = self.ns
        ahead = Time(sec=status.header.stamp.sec + AHEAD_S, nanosec=status.header.stamp.nanosec)
        for k in (1, 2) if not self.only_moves else ():  # jump-ahead statuses in the driver's session
            forged = copy.deepcopy(status)
            forged.step, forged.header.stamp = 10**9 + k, ahead
            forged.auth.mac = b""
            self._send("status", forged, contract.status_topic(ns))
        declaration = SourceDeclaration(agent_id="agent_0", episode=status.episode, step=status.step,
                                        map_stamp=status.map_stamp, cell_i=0, cell_j=0, mass=1.0)
        declaration.header.stamp, declaration.header.frame_id = status.header.stamp, contract.MAP_FRAME
        if not self.only_moves:
            self._send("declaration", declaration, contract.declaration_topic(ns))
        for a in IDS:
            if a == self.lost or self.lost is None:
                move = AgentMove(agent_id=a, episode=status.episode, step=status.step, action=4,
                                 sender=self.senders.get(a, "ghost"))
                move.header.frame_id = contract.MAP_FRAME
                self._send(f"move {a}", move, contract.move_topic(ns, a))
        if self.lost is not None:  # a lost agent "alive": its pose and reading stamped an hour ahead
            for stamp in (status.header.stamp, ahead):
                pose = PoseStamped()
                pose.header.stamp, pose.header.frame_id = stamp, contract.MAP_FRAME
                pose.pose.position.x = pose.pose.position.y = 0.5
                pose.pose.orientation.w = 1.0
                self.pubs[f"pose {self.lost}"].publish(pose)
                reading = RadiationReading(agent_id=self.lost, value=1.0, pose_digest=message_digest(pose))
                reading.header.stamp, reading.header.frame_id = stamp, contract.MAP_FRAME
                self._send(f"reading {self.lost}", reading, contract.radiation_topic(ns, self.lost))


def main() -> None:
    import argparse
    import signal
    import threading

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    parser = argparse.ArgumentParser()
    parser.add_argument("--namespace", required=True)
    parser.add_argument("--lost", default=None)
    parser.add_argument("--wrong-key", required=True)
    args = parser.parse_args()
    stop = threading.Event()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    executor = SingleThreadedExecutor()
    ghosts = []
    for mode in MODES:
        node = rclpy.create_node(f"ghost_{mode.replace(' ', '_')}", namespace=args.namespace)
        ghost = Intruder(node, args.namespace, mode, args.wrong_key, lost=args.lost)
        ghost.active = False
        ghost.min_period_s = 0.05  # 20 bursts a second, each of every kind: 400-500 messages a second
        executor.add_node(node)
        ghosts.append(ghost)

    def go(*_) -> None:
        for g in ghosts:
            g.active = True

    signal.signal(signal.SIGUSR1, go)
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    said = False
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        if not said and all(g.captured for g in ghosts) and all(g.senders.get(args.lost) for g in ghosts):
            print("CAPTURED", flush=True)
            said = True
    print(f"SENT {sum(g.sent for g in ghosts)}", flush=True)
    executor.shutdown()
    for g in ghosts:  # leave the domain cleanly: the team's writers stop serving these readers at once
        g.node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
