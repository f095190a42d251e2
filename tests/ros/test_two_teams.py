"""Two complete teams share one ROS domain under two namespaces and never hear each other.

/team1 is started by ``medc-launch --namespace /team1`` (one process per node, each moved with
``-r __ns:=/team1``); /team2 is the team medc.launch.py describes for ``namespace:=/team2``, its
nodes run as launch_ros runs them (console script, ``__node``/``__ns`` remaps, the package's
parameter file, then the launch's values). Both play their seeds' first episodes exactly as the
training environment does (a foreign move or status would change them), every endpoint of a team's
topics belongs to a node of that team, and no node reports a second driver or a foreign move; then
both are stopped as Ctrl-C stops them.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from medc_common import contract
from ros_helpers import load_launch_file, reference_episodes, stop_node_processes

SCENARIO = {"agents": 2, "walls": 1, "grid": 10, "max_steps": 20}
EPISODES = 3
SEEDS = {"/team1": 1, "/team2": 2}
#: Diagnostics that would mean the two teams heard each other.
CROSSTALK = ("another driver", "second graph", "another process publishes moves", "foreign",
             "did not publish")
BINDIR = Path(sys.executable).parent
#: Every team's topics, relative to its namespace.
TEAM_TOPICS = {"map", "episode", "episode_result", "team/policy", "team/source_estimate",
               "team/source_posterior", "team/source_declared",
               *(f"{a}/{kind}" for a in contract.agent_ids(SCENARIO["agents"])
                 for kind in ("pose", "radiation", "move", "policy"))}


def team_nodes(ns: str) -> set[tuple[str, str]]:
    """(node name, namespace) of every node of the team under ``ns``."""
    return {("medc_sim", ns), *((contract.agent_node_name(i), ns) for i in range(SCENARIO["agents"]))}


def launch_commands(spec_nodes: list[dict]) -> list[list[str]]:
    """The command line of each node of ``team_nodes``, as launch_ros builds it for a Node."""
    from medc_bringup.launcher import ros_args

    out = []
    for node in spec_nodes:
        params_file, params = node["parameters"]
        args = ros_args(node["name"], params, node["namespace"])  # --ros-args, 2 remaps, -p ...
        out.append([str(BINDIR / node["executable"]), *args[:5], "--params-file", params_file, *args[5:]])
    return out


class Watch:
    """A node outside both teams that records results, moves, diagnostics and the graph."""

    NAME = "two_teams_watch"

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from medc_interfaces.msg import AgentMove, EpisodeStatus

        self.node = rclpy.create_node(self.NAME)
        self.results: dict[str, list] = {ns: [] for ns in SEEDS}
        #: (namespace, agent id) -> the senders of the moves heard on that agent's move topic.
        self.senders: dict[tuple[str, str], set[str]] = {}
        self.statuses: dict[str, int] = dict.fromkeys(SEEDS, 0)
        self.diagnostics: list = []
        #: Topic -> namespaces of the nodes at its ends, as seen in any snapshot while spinning.
        self.graph: dict[str, set[str]] = {}
        self._snapped = 0.0
        sub = self.node.create_subscription
        for ns in SEEDS:
            sub(EpisodeStatus, contract.results_topic(ns), self.results[ns].append, contract.RESULTS_QOS)
            sub(EpisodeStatus, contract.status_topic(ns), lambda m, ns=ns: self._count(ns),
                contract.RELIABLE_QOS)
            for agent in contract.agent_ids(SCENARIO["agents"]):
                sub(AgentMove, contract.move_topic(ns, agent),
                    lambda m, key=(ns, agent): self.senders.setdefault(key, set()).add(m.sender),
                    contract.RELIABLE_QOS)
        sub(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: self.diagnostics.extend(m.status),
            contract.DIAGNOSTICS_QOS)

    def _count(self, ns: str) -> None:
        self.statuses[ns] += 1

    def spin(self, seconds: float, until=lambda: False) -> bool:
        import rclpy

        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=0.05)
            if time.monotonic() - self._snapped > 0.25:
                self.snapshot()
            if until():
                return True
        return False

    def complete(self) -> bool:
        """Whether a node of each team was seen at every one of its team's topics and every node of
        both teams was heard on /diagnostics (nodes beat at 1 Hz: a fast team can finish its episodes
        before the watch has heard a beat of each)."""
        return (all(self.graph.get(f"{ns}/{topic}") for ns in SEEDS for topic in TEAM_TOPICS)
                and all(team_nodes(ns) <= self.beats() for ns in SEEDS))

    def beats(self) -> set[tuple[str, str]]:
        """(node name, namespace) of every heartbeat heard."""
        return {(s.name, kv.value) for s in self.diagnostics for kv in s.values if kv.key == "namespace"}

    def snapshot(self) -> None:
        """Add the namespaces of the nodes that publish or subscribe to each topic now (this one
        aside): nodes are discovered one by one, and a team may finish before all are seen at once."""
        n = self.node
        self._snapped = time.monotonic()
        for topic, _ in n.get_topic_names_and_types():
            ends = [*n.get_publishers_info_by_topic(topic), *n.get_subscriptions_info_by_topic(topic)]
            # (an endpoint whose node is not discovered yet shows as _NODE_NAMESPACE_UNKNOWN_)
            seen = {e.node_namespace for e in ends
                    if e.node_name != self.NAME and not e.node_namespace.startswith("_NODE_")}
            self.graph.setdefault(topic, set()).update(seen)


def run_two_teams(config: Path, tmp_path: Path, watch: Watch) -> dict:
    """Start both teams; once each has played EPISODES and the watch has seen every node of both
    (nodes are discovered one by one), stop them as Ctrl-C does. Returns team1's launcher summary;
    asserts that every process ended cleanly."""
    team2 = launch_commands(load_launch_file().team_nodes({
        "namespace": "/team2", "config": str(config), "seed": str(SEEDS["/team2"])}))
    launcher = [str(BINDIR / "medc-launch"), "--config", str(config), "--namespace", "/team1", "--seed",
                str(SEEDS["/team1"]), "--quiet", "--timeout", "400"]
    names = ["team1", *(f"team2-{i}" for i in range(len(team2)))]
    logs = {name: (tmp_path / f"{name}.log").open("w") for name in names}
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen(launcher, stdout=subprocess.PIPE, stderr=logs["team1"], text=True))
        procs += [subprocess.Popen(c, stdout=logs[name], stderr=subprocess.STDOUT)
                  for name, c in zip(names[1:], team2)]
        # Seven node processes start on a shared machine (2 to 3 s of CPU each): minutes when loaded;
        # the launcher's own --timeout is longer, so it is still running when this ends.
        done = watch.spin(300, lambda: all(len(r) >= EPISODES for r in watch.results.values())
                          and watch.complete())
        assert done, ({ns: len(r) for ns, r in watch.results.items()}, watch.graph, watch.beats())
    finally:
        stop_node_processes(procs, wait_s=60)  # the launcher stops its own nodes
        for log in logs.values():
            log.close()
    texts = {name: (tmp_path / f"{name}.log").read_text() for name in names}
    bad = {k: t[-2000:] for k, t in texts.items() if "Traceback" in t or "FATAL" in t}
    assert not bad, bad
    assert all(p.returncode == 0 for p in procs), [(p.args[0], p.returncode) for p in procs]
    return json.loads(procs[0].stdout.read().strip().splitlines()[-1])


@pytest.mark.timing
@pytest.mark.ros
def test_two_teams_share_a_domain_under_two_namespaces(rclpy_context, bundles, tmp_path):
    config = tmp_path / "launch.yaml"
    config.write_text("".join(f"{k}: {v}\n" for k, v in SCENARIO.items()) + f"policy: {bundles['a']}\n")
    watch = Watch()
    try:
        summary = run_two_teams(config, tmp_path, watch)
        # Results team1 published after the watch stopped spinning wait in the watch's reader.
        watch.spin(60, lambda: len(watch.results["/team1"]) >= len(summary["episode_lengths"]))
    finally:
        watch.node.destroy_node()

    # Each team played its own seed's episodes, exactly as training's environment plays them.
    for ns, seed in SEEDS.items():
        lengths, successes, _ = reference_episodes(bundles["a"], EPISODES, seed=seed, **SCENARIO)
        got = watch.results[ns][:EPISODES]
        assert [(r.episode_length, r.success) for r in got] == list(zip(lengths, successes)), ns
        assert len({r.session for r in got}) == 1
    assert watch.results["/team1"][0].session != watch.results["/team2"][0].session
    # What team1's launcher printed when stopped (its monitor may not have had the latest yet).
    printed = summary["episode_lengths"]
    assert printed == [r.episode_length for r in watch.results["/team1"][:len(printed)]], printed
    # Each agent's move topic carried the moves of one node, never one of the other team's (a team
    # steps fast: this watch may be matched to a move publisher only after its team's last move).
    assert all(len(senders) == 1 for senders in watch.senders.values()), watch.senders
    heard = {ns: set().union(*(v for (n, _), v in watch.senders.items() if n == ns)) for ns in SEEDS}
    assert all(heard.values()) and not heard["/team1"] & heard["/team2"], heard

    # The same topics under each namespace, nothing under /medc, and every endpoint of a team's
    # topic is a node of that team.
    graph = watch.graph
    suffixes = {ns: {t[len(ns) + 1:] for t in graph if t.startswith(ns + "/")} for ns in SEEDS}
    assert suffixes["/team1"] == suffixes["/team2"] and suffixes["/team1"] >= TEAM_TOPICS, suffixes
    assert not [t for t in graph if t.startswith(contract.DEFAULT_NAMESPACE + "/")]
    for ns in SEEDS:
        for topic in (t for t in graph if t.startswith(ns + "/")):
            assert graph[topic] <= {ns}, (topic, graph[topic])

    # Heartbeats from every node of both teams, named by namespace; no crosstalk reported.
    beats = watch.beats()
    for ns in SEEDS:
        assert team_nodes(ns) <= beats, beats
    crosstalk = [s.message for s in watch.diagnostics if any(w in s.message for w in CROSSTALK)]
    assert not crosstalk, crosstalk[:3]
