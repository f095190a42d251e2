"""medc-sim: the simulator node. It plays the part of the UAV team's drivers.

Publishes, per agent, its pose (geometry_msgs/PoseStamped, frame "map") and radiation reading
(medc_interfaces/RadiationReading), both with sensor-data QoS; the walls map (nav_msgs/
OccupancyGrid, transient local) and one medc_interfaces/EpisodeStatus per team step. Applies each
agent's medc_interfaces/AgentMove. Topic names and QoS: medc_common.contract and docs/ros-reference.md.
The names are relative to the node's namespace (``/medc`` unless ``-r __ns:=/team2`` moves it).

Modes:
  stepped   waits for every agent's move, then steps (at most ``rate_hz`` steps/s; 0 = no limit).
            While waiting it re-publishes the step every ``resend_s`` so lost sensor-data
            messages or late-starting agents cannot stall the team. An agent with no move
            ``move_timeout_s`` after the step's first move stays in place and is taken out: later
            steps do not wait for it until it moves again (docs/ros-reference.md, "A lost UAV"; the move
            rules: medc_sim.moves; other drivers on the topics: medc_sim.watch).
  realtime  steps every 1/``rate_hz`` s with the moves received; an agent without a move stays.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import torch
from geometry_msgs.msg import PoseStamped
from medc_common import contract
from medc_common.auth_node import declare_auth, message_digest
from medc_common.health import Health, run_id
from medc_common.params import count, declare, number, seconds
from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node

from medc_sim import messages
from medc_sim.declarations import Declarations
from medc_sim.move_watch import MoveFaults, StepWatch
from medc_sim.moves import MoveBook, MoveRejected
from medc_sim.sim_core import EpisodeResult, SimConfig, SimCore
from medc_sim.start_gate import StartGate
from medc_sim.watch import GraphWatch


@dataclass(frozen=True)
class SimParameters:
    """A simulator node's parameters as declared (:func:`declare_sim_parameters`; their descriptions
    are there and in ``medc-sim --help``)."""

    namespace: str
    cfg: SimConfig
    mode: str
    rate_hz: float
    resolution: float
    resend_s: float
    max_episodes: int
    stall_timeout_s: float
    move_timeout_s: float
    threads: int
    wait_for: int
    results_readers: int


def declare_sim_parameters(node: Node) -> SimParameters:
    """Declare every parameter of a simulator node on ``node`` and return their values (ValueError for
    a bad mode or rate)."""
    p = lambda *a, **k: declare(node, *a, **k)  # noqa: E731
    namespace = p("namespace", "", contract.NAMESPACE_HELP, True)
    cfg = SimConfig(
        agents=p("agents", 3, "Number of agents in the team", True),
        walls=p("walls", 2, "Number of wall segments", True),
        grid=p("grid", 30, "Grid side in cells", True),
        max_steps=p("max_steps", 100, "Steps before an episode is truncated", True),
        seed=p("seed", 0, "Seed of the environment: same seed = same episodes as training", True),
        noise=p("noise", False, "Poisson noise on readings (paper-simple; realistic always counts it)",
                True),
        sensing=p(
            "sensing",
            "paper-simple",
            "Sensing model, a preset (paper-simple, realistic; docs/ros-reference.md, "
            "'Sensor model'): how readings are made and how near an agent must come to the source",
            True,
        ),
        end_on=p(
            "end_on", "source",
            "What ends an episode besides max_steps: 'source' (a UAV finds it, as in training), "
            "'declaration' (the team's SourceDeclaration; agents need source_ends_episode:=false) or "
            "'either' (whichever comes first)",
            True,
        ),
        world=p(
            "world", "grid",
            "The world simulated: 'grid' (the sensing preset's grid world) or 'radbench' (the field "
            "benchmark's: solid obstructions, walls 0..7, grid 20 or 30, sensing realistic, end_on source; "
            "docs/ros-reference.md, 'The benchmark's world')",
            True,
        ),
    )
    mode = p("mode", "stepped", "'stepped' (wait for all moves) or 'realtime' (fixed rate)", True)
    if mode not in ("stepped", "realtime"):
        raise ValueError(f"mode must be 'stepped' or 'realtime', got {mode!r}")
    rate_hz = number("rate_hz", p("rate_hz", 0.0, "Team steps per second (stepped: upper limit, 0 = none; "
                                  "realtime: the step rate, must be > 0)", True))
    if mode == "realtime" and rate_hz <= 0:
        raise ValueError("realtime mode needs rate_hz > 0")
    return _declare_stepping(p, namespace, cfg, mode, rate_hz)


def _declare_stepping(p, namespace: str, cfg: SimConfig, mode: str, rate_hz: float) -> SimParameters:
    """The rest of :func:`declare_sim_parameters` (``p`` declares one parameter)."""
    resolution = number("resolution", p("resolution", 1.0, "Cell side in metres (map frame)", True),
                        zero_ok=False)
    resend_s = seconds("resend_s", p("resend_s", 0.5, "Stepped mode: re-publish a step whose moves are "
                                     "missing after this many seconds", True))
    max_episodes = count("episodes", p("episodes", 0, "Stop stepping after this many episodes (0 = never)",
                                       True))
    stall_timeout_s = seconds("stall_timeout_s", p(
        "stall_timeout_s", 2.0,
        "Stepped mode: a step whose moves are missing for this long is logged once, naming the agents",
        True,
    ))
    move_timeout_s = seconds("move_timeout_s", p(
        "move_timeout_s", 3.0,
        "Stepped mode: an agent with no move this long (seconds) after the step's first move stays "
        "in place and is taken out of the team (later steps do not wait for it) until it moves "
        "again; 0: wait for ever",
        True,
    ), zero_ok=True)
    threads = int(p("torch_threads", 1, "CPU threads for the environment", True))
    wait_for = int(p(
        "wait_for_subscribers", cfg.agents,
        "Publish the first step once this many other nodes subscribe to the episode status (the "
        "agents; a recorder adds itself) and, when > 0, every agent's move publisher is there (a "
        "recorder is no agent)", True))
    results_readers = int(p(
        "wait_for_results_readers", 0,
        "Also wait before the first step until this many nodes read the episode results (the "
        "launcher's monitor, a recorder), and before a finished simulator exits (at least 1)", True))
    return SimParameters(namespace, cfg, mode, rate_hz, resolution, resend_s, max_episodes, stall_timeout_s,
                         move_timeout_s, threads, wait_for, results_readers)


class SimNode(Node):
    """The simulator node (see the module docstring), made of parts each built from what it needs:
    the core (medc_sim.sim_core), the move book (medc_sim.moves), the move faults and the step watch
    (medc_sim.move_watch), the graph watch (medc_sim.watch), the declarations
    (medc_sim.declarations) and the start gate (medc_sim.start_gate)."""

    def __init__(self, node_name: str = "medc_sim", **kwargs) -> None:
        kwargs.setdefault("namespace", contract.DEFAULT_NAMESPACE)
        super().__init__(node_name, **kwargs)
        prm = declare_sim_parameters(self)
        cfg = prm.cfg
        #: The team's namespace (fully qualified, for messages) and the one names are built with
        #: (None: relative to the node's namespace; contract.team_namespace).
        self.namespace_, self.names_ns = contract.team_namespace(self.get_namespace(), prm.namespace)
        self.mode, self.rate_hz, self.resolution = prm.mode, prm.rate_hz, prm.resolution
        self.resend_s, self.max_episodes = prm.resend_s, prm.max_episodes
        self.stall_timeout_s, self.move_timeout_s = prm.stall_timeout_s, prm.move_timeout_s
        #: Per-run id of this driver, sent with every status (EpisodeStatus.session).
        self.session = run_id()

        # The environment's tensors are tiny; threads only add contention with the agent nodes.
        torch.set_num_threads(max(1, prm.threads))
        self.core = SimCore(cfg)  # an unknown sensing preset: ValueError naming the presets
        self.ids = contract.agent_ids(self.core.num_agents)
        self.book = MoveBook(self.core.num_agents, self.core.num_actions)
        #: The grid in the map frame (REP 103): at the origin, identity orientation.
        self.geometry = contract.GridGeometry(cfg.grid, cfg.grid, self.resolution)
        self.dropped = 0
        self.finished = False
        self.episode_listeners: list[Callable[[EpisodeResult], None]] = []
        self._step_stamp = None
        #: Seconds from publishing a step to receiving the team's last move, per step (latest 100k).
        self.latencies: deque[float] = deque(maxlen=100_000)

        self._connect(cfg)
        self.gate = StartGate(self.status_pub, self.move_subs, self.results_pub, prm.wait_for,
                              prm.results_readers)
        self._start_timers()
        walls_words = "obstructions at most" if cfg.world == "radbench" else "walls"
        self.get_logger().info(
            f"simulating {cfg.agents} agents, {cfg.walls} {walls_words}, {cfg.grid}x{cfg.grid} grid in the "
            f"{cfg.world} world, "
            f"seed {cfg.seed}, sensing {cfg.sensing}{' (Poisson counts)' if self.core.noise else ''}, "
            f"{self.mode} mode on {self.namespace_}"
        )

    def _connect(self, cfg: SimConfig) -> None:
        """The team's publishers, the move (and declaration) subscriptions, diagnostics."""
        ns = self.names_ns
        self.pose_pubs = [
            self.create_publisher(PoseStamped, contract.pose_topic(ns, a), contract.SENSOR_QOS)
            for a in self.ids
        ]
        self.reading_pubs = [
            self.create_publisher(RadiationReading, contract.radiation_topic(ns, a), contract.SENSOR_QOS)
            for a in self.ids
        ]
        self.map_pub = self.create_publisher(OccupancyGrid, contract.map_topic(ns), contract.LATCHED_QOS)
        self.results_pub = self.create_publisher(
            EpisodeStatus, contract.results_topic(ns), contract.RESULTS_QOS
        )
        self.status_pub = self.create_publisher(
            EpisodeStatus, contract.status_topic(ns), contract.RELIABLE_QOS
        )
        self.health = Health(self, "driver", self._summary)
        #: Signing of what it publishes and checking of moves and declarations (medc_common.auth_node).
        self.auth = declare_auth(self, self.session, self.health)
        self._map_digest = b""
        # The declaration subscription comes before the move subscriptions: a declaration and the
        # last move of its step that wait together are taken in that order.
        #: The team's declarations, when one may end an episode (medc_sim.declarations).
        self.declarations = None if cfg.end_on == "source" else Declarations(
            self, ns, self.namespace_, self.ids, self.core, self.book, self.health, running=self._running,
            map_stamp=lambda: self._map_stamp, finish=self._finish_episode, drop=self._count_drop,
            auth=self.auth)
        self.move_subs = [
            self.create_subscription(
                AgentMove,
                contract.move_topic(ns, a),
                lambda m, a=a: self._on_move(a, m),
                contract.RELIABLE_QOS,
            )
            for a in self.ids
        ]
        #: The ``moves`` condition: duplicate agent ids, conflicting and foreign moves.
        self.move_faults = MoveFaults(self.health, self.get_logger(), self.create_timer)
        #: The step in play's timing; in stepped mode, its re-sends, stalls and agents taken out.
        self.steps = StepWatch(self.book, self.ids, self.health, self.get_logger(), send=self._send_state,
                               advance=self._advance, running=self._running,
                               resend_s=self.resend_s, stall_timeout_s=self.stall_timeout_s,
                               move_timeout_s=self.move_timeout_s, rate_hz=self.rate_hz)
        #: Other drivers' statuses and maps on this namespace (a second graph, a hostile map).
        self.watch = GraphWatch(self, ns, self.namespace_, self.session, self.health,
                                started=lambda: self.started, finished=lambda: self.finished,
                                republish=lambda: self.map_pub.publish(self.map_msg()))
        if self.mode == "stepped" and self.move_timeout_s > 0:
            self.create_timer(min(0.1, self.move_timeout_s / 4), self.steps.move_timeout_tick)

    def _start_timers(self) -> None:
        """The start gate, and the stepping timers of the mode."""
        self.started = False
        self._start_timer = self.create_timer(0.02, self._try_start)
        if self.mode == "realtime":
            self.create_timer(1.0 / self.rate_hz, self._realtime_tick)
        else:
            self.create_timer(max(self.resend_s, 0.01), self.steps.resend_tick)
            if self.rate_hz > 0:
                self.create_timer(1.0 / self.rate_hz, self._rate_tick)

    # -- publishing ----------------------------------------------------------------------
    def _try_start(self) -> None:
        """Start once the team and the results readers are matched (medc_sim.start_gate)."""
        missing = self.gate.missing()
        if missing and not self.gate.expired():
            return
        if missing:
            self.get_logger().warning(f"starting with {' and '.join(missing)}")
        self._start_timer.cancel()
        self.destroy_timer(self._start_timer)
        self.started = True
        self._begin_episode()

    def _begin_episode(self) -> None:
        self._map_stamp = self.get_clock().now().to_msg()
        grid = self.map_msg()
        # Statuses name the map's digest: under a mission key agents take no other map.
        self._map_digest = message_digest(grid) if self.auth.enabled else b""
        self.map_pub.publish(grid)
        self._publish_step()

    def map_msg(self) -> OccupancyGrid:
        """The walls map of the episode in play."""
        self.watch.own_map(self._map_stamp)
        return messages.grid_msg(self.core.walls(), self._map_stamp, self.resolution)

    def _summary(self) -> dict[str, str]:
        return {"namespace": self.namespace_, "session": self.session, "episode": str(self.core.episode),
                "step": str(self.core.step),
                "episodes_done": str(len(self.core.results)), "resends": str(self.steps.resends),
                "dropped_moves": str(self.dropped), "resent_moves_ignored": str(self.book.resent),
                "conflicting_moves": str(self.book.conflicts),
                "lost": ", ".join(self.ids[i] for i in sorted(self.book.lost)) or "none",
                **self.auth.summary()}

    def _publish_step(self) -> None:
        """Publish the current state as a new step and wait for its moves."""
        self._step_stamp = self.get_clock().now().to_msg()
        self.book.open(self.core.episode, self.core.step)
        self.steps.opened()
        self._send_state()

    def _send_state(self) -> None:
        stamp = self._step_stamp
        noise = self.core.noise
        sign, ns = self.auth.sign, self.namespace_
        for i, (cell, value) in enumerate(zip(self.core.positions(), self.core.readings())):
            pose = messages.pose_msg(cell, stamp, self.geometry)
            self.pose_pubs[i].publish(pose)
            # Poisson counts: the variance is the mean.
            variance = value if noise else 0.0
            reading = messages.reading_msg(self.ids[i], value, variance, stamp)
            if self.auth.enabled:  # the signed reading vouches for the pose
                reading.pose_digest = message_digest(pose)
            self.reading_pubs[i].publish(sign(reading, contract.radiation_topic(ns, self.ids[i])))
        core = self.core
        status = messages.status_msg(self.ids, core.episode, core.step, stamp, self._map_stamp,
                                     session=self.session)
        status.map_digest = self._map_digest
        self.status_pub.publish(sign(status, contract.status_topic(ns)))
        self.steps.sent()

    def _publish_done(self, result: EpisodeResult) -> None:
        stamp = self.get_clock().now().to_msg()
        msg = messages.status_msg(self.ids, result.episode, result.length, stamp, self._map_stamp, result,
                                  self.session)
        msg.map_digest = self._map_digest
        self.status_pub.publish(self.auth.sign(msg, contract.status_topic(self.namespace_)))
        self.results_pub.publish(self.auth.sign(msg, contract.results_topic(self.namespace_)))

    # -- stepping ------------------------------------------------------------------------
    def _on_move(self, topic_agent: str, msg) -> None:
        if not self.auth.admit(msg, contract.move_topic(self.namespace_, topic_agent), "move"):
            self.dropped += 1
            return
        if self.auth.enabled and msg.sender != msg.auth.sender:
            self.dropped += 1
            self.auth.refuse("move", f"move of {topic_agent} names sender {str(msg.sender)[:40]!r} but was "
                                     f"signed by {str(msg.auth.sender)[:40]!r}")
            return
        try:
            if msg.agent_id != topic_agent:
                raise MoveRejected(f"move on {topic_agent}'s topic names agent {msg.agent_id!r}")
            taken = self.book.offer(msg.agent_id, int(msg.episode), int(msg.step), int(msg.action),
                                    str(msg.sender))
            if taken is not None:
                self.steps.took()
            self.steps.report_returned()
            if taken is None:
                return  # a re-sent move, or one for the step just applied: executed once already
        except MoveRejected as exc:  # a duplicate agent id, a conflicting or a foreign move
            if self.move_faults.refused(msg.agent_id, exc):
                self.dropped += 1
            return
        # Team decision latency: this step's state published -> the last move received.
        latency = self.steps.latency() if self.book.complete else None
        if latency is not None:
            self.latencies.append(latency)
        if self.mode == "stepped" and self.rate_hz <= 0 and self.book.complete:
            self._advance()

    def _running(self) -> bool:
        """Whether the simulator has started and not finished."""
        return self.started and not self.finished

    def _count_drop(self) -> None:
        self.dropped += 1

    @property
    def resends(self) -> int:
        """Steps re-published for moves missing."""
        return self.steps.resends

    def _rate_tick(self) -> None:
        if self.started and self.book.complete:
            self._advance()

    def _realtime_tick(self) -> None:
        if self.started:
            self._advance()

    def _advance(self) -> None:
        if self.finished:
            return
        result = self.core.advance(self.book.actions())
        if result.finished is not None:
            self._finish_episode(result.finished)
        else:
            self._publish_step()

    def _finish_episode(self, finished: EpisodeResult) -> None:
        self._publish_done(finished)
        for listener in self.episode_listeners:
            listener(finished)
        if self.max_episodes and len(self.core.results) >= self.max_episodes:
            self.finished = True
            self.get_logger().info(f"{len(self.core.results)} episodes done; simulator idle")
            return
        self._begin_episode()
