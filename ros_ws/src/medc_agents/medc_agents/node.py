"""The agent node: one per agent; observes the team, runs its policy bundle, publishes its move.

Subscribes (names and QoS: medc_common.contract, docs/ros-reference.md): every team member's pose and
radiation reading, the walls map, the episode status, and its own and the team's policy topics.
Publishes its medc_interfaces/AgentMove on ``<ns>/<agent_id>/move``. Every name is relative to
the node's namespace (``/medc`` unless ``-r __ns:=/team2`` moves it), the registry bridge's
service included.

The policy is a bundle path or a classical controller's name (``gradient``, ``greedy``,
``infotaxis``: the node then decides its move with the controller's function on its team state,
medc_agents.controller; start it with the ``agents`` and ``grid`` parameters, as there is no
manifest). It is swapped at runtime by setting the ``policy`` parameter or by publishing a bundle
path or a controller's name on the policy topics. A content id on the policy topic is passed to
the registry bridge's ``fetch_bundle`` service, which verifies the bundle and sends back its local
path. A bundle that
fails validation is refused (the parameter set fails with the reason) and the old one keeps
running. No file and no message can take the node down: every exception of a swap (a
RecursionError or MemoryError from a hostile file included) ends as a logged refusal.

:class:`AgentNode` owns its parts, each built from what it reads and reports to and tested without a
node: the team observer and guards (medc_agents.team_state, medc_agents.guard), the policy slot and
its swaps (medc_agents.policy_swaps), the team's estimate (medc_agents.estimate), the map faults
(medc_agents.map_faults), the watches over its team (medc_agents.team_watch), the signed poses and
maps it holds (medc_agents.signed_inputs), its decisions (:class:`Decider`) and its moves out
(:class:`MoveOut`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import torch
from geometry_msgs.msg import PoseStamped
from medc_common import contract
from medc_common.auth_node import declare_auth
from medc_common.health import Health, run_id
from medc_common.params import count, declare, number, seconds
from medc_interfaces.msg import AgentMove, EpisodeStatus, RadiationReading
from medc_training.bundle import MAX_FORWARD_SECONDS
from medc_training.bundle.runtime import RUNTIMES
from medc_training.controllers import CONTROLLERS
from medc_training.envs.names import DEFAULT_APPLICATION
from medc_training.envs.target_localization import ACTIONS, DEFAULT_OBSERVATION
from medc_training.envs.tl_observation import observation_shape
from medc_training.envs.tl_sensing import DEFAULT_SENSING, SENSING_PRESETS
from medc_training.untrusted import printable
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node
from std_msgs.msg import String

from medc_agents import guard
from medc_agents.bench_team import check_endgame_tau, check_world, endgame_move, model_words, team_model
from medc_agents.controller import controller_move, controller_name, controller_scenario
from medc_agents.estimate import TeamEstimate
from medc_agents.map_faults import MapFaults
from medc_agents.policy_slot import (
    PolicyRejected,
    PolicySlot,
    read_policy_manifest,
    shown,
)
from medc_agents.policy_swaps import BridgeFetch, PolicySwaps, refusal_reason
from medc_agents.signed_inputs import SignedInputs
from medc_agents.team_messages import EDGE_TOLERANCE_CELLS
from medc_agents.team_state import TeamObserver
from medc_agents.team_watch import (
    ClaimWatch,
    DriverWatch,
    NoteLog,
    OldStatuses,
    ReadingWatch,
    StallWatch,
    StatusIntake,
    TeamWatch,
)

#: Moves a target-localization agent chooses from (N, NE, E, ..., NW): the environment's own.
NUM_ACTIONS = len(ACTIONS)
#: Default of the agent's ``stall_timeout_s`` (docs/ros-reference.md, "Stalls and diagnostics"):
#: longer than a driver's re-send period (the simulator's resend_s is 0.5 s), so one lost
#: best-effort message is not reported.
STALL_TIMEOUT_S = 2.0
#: Statuses below the step answered are summed up in one log line at most this often (seconds).
OLD_STATUS_SUMMARY_S = 10.0


def scenario_from_bundle(policy: str, agents: int, grid: int, observation: str,
                         application: str | None = None) -> tuple[int, int, str]:
    """(agents, grid, observation) an agent runs with: each value given (> 0, non-empty) wins,
    the others come from the manifest of the bundle at ``policy`` (``environment.agents``,
    ``environment.grid``, ``observation.name``; a bundle without an observation name takes
    'maps'). A controller's name as ``policy`` has no manifest: ``agents`` and ``grid`` must be
    given (an empty observation stays empty: the default variant); ``application``, when given,
    must be target localization for a controller.

    Raises:
        PolicyRejected: no policy, an unreadable or invalid bundle, or a value neither given nor
        in the manifest; the message says which and what to pass.
    """
    if not policy:
        raise PolicyRejected("no policy bundle: start the agent with -p policy:=<bundle.safetensors> "
                             "(its manifest gives the team size, grid and observation) or with a "
                             "controller, e.g. -p policy:=greedy -p agents:=3 -p grid:=30")
    check_scenario_size(agents, grid)
    name = controller_name(policy)
    if name is not None:
        try:
            controller_scenario(name, agents, grid, application)
        except ValueError as exc:
            raise PolicyRejected(str(exc)) from None
        return agents, grid, observation
    if agents > 0 and grid > 0 and observation:
        return agents, grid, observation
    from medc_training.bundle import manifest_observation

    manifest = read_policy_manifest(policy)
    env = manifest.get("environment") or {}

    def from_manifest(key: str, given: int) -> int:
        if given > 0:
            return given
        value = env.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise PolicyRejected(f"policy bundle {shown(policy)} names no environment.{key} in its manifest: "
                                 f"pass -p {key}:=<n>")
        return value

    agents, grid = from_manifest("agents", agents), from_manifest("grid", grid)
    check_scenario_size(agents, grid)  # the manifest's are bounded already; this says so again
    return agents, grid, observation or manifest_observation(manifest)


def check_scenario_size(agents: int, grid: int) -> None:
    """Refuse a team or grid larger than any bundle may name (``MAX_BUNDLE_AGENTS``,
    ``MAX_BUNDLE_GRID``), before anything is allocated for it: the agent's memory grows faster
    than the grid's area. Raises PolicyRejected saying the bound."""
    from medc_training.bundle import MAX_BUNDLE_AGENTS, MAX_BUNDLE_GRID

    for key, value, most in (("agents", agents, MAX_BUNDLE_AGENTS), ("grid", grid, MAX_BUNDLE_GRID)):
        if value > most:
            raise PolicyRejected(f"{key} {value} is over the {most} an agent runs with "
                                 f"(MAX_BUNDLE_{key.upper()}); pass -p {key}:=<n> with n <= {most}")


def endgame_words(tau: float) -> str:
    """What the log lines of the running policy add for the classical endgame (empty when off)."""
    if tau >= 1.0:
        return ""
    return f"; classical endgame on at tau {tau:g} (a shortest path once the posterior's mode holds it)"


def running_words(slot, observer, num_agents: int, grid: int, prm: AgentParameters) -> str:
    """The log line that says which policy an agent runs, on what, in which world, and whether the
    classical endgame is on."""
    return (f"running policy {slot.current.description} for {observer.agent_id} of {num_agents} agents on "
            f"a {grid}x{grid} grid (observation {observer.observation.name}), sensing "
            f"{model_words(observer.sensing)}, {prm.world} world{slot.runs_in()}"
            f"{endgame_words(prm.endgame_tau)}")


def default_node_name(agent_id: str | None) -> str:
    """``medc_<agent_id>`` (e.g. medc_agent_1), unique per agent; ``medc_agent`` for an id that is
    not of the form agent_<i>."""
    if agent_id and (m := contract.AGENT_ID_PATTERN.match(agent_id)):
        return contract.agent_node_name(int(m.group(1)))
    return "medc_agent"


def _declare_scenario(node: Node, agent_id: str | None) -> dict:
    """Declare the parameters of an agent node that say its team, scenario, registry and policy limits
    (the first part of :func:`declare_agent_parameters`); returns their values by AgentParameters field."""
    p = lambda *a, **k: declare(node, *a, **k)  # noqa: E731
    agent_id = p(
        "agent_id", agent_id or "agent_0", "This agent's id: agent_<i>, i = env index", True
    )
    namespace = p("namespace", "", contract.NAMESPACE_HELP, True)
    num_agents = p("agents", 0, "Number of agents in the team; 0: the policy bundle's manifest's", True)
    grid = p("grid", 0, "Grid side in cells (an agent-centred observation then follows each map's "
                     "size); 0: the policy bundle's manifest's", True)
    observation = p(
        "observation",
        "",
        "Observation variant a policy must take (maps, maps+estimate, egoR, egoR+estimate, each "
        "optionally with +posterior); "
        "empty: the one each policy bundle's manifest names",
        True,
    )
    resolution = p("resolution", 0.0, "Cell side in metres a map must have; 0: the map's own", True)
    sensing = p(
        "sensing",
        DEFAULT_SENSING,
        f"Sensing model of the team's readings, a preset ({', '.join(sorted(SENSING_PRESETS))}; "
        "docs/ros-reference.md, 'Sensor model'); a bundle trained under another is refused",
        True,
    )
    if sensing not in SENSING_PRESETS:
        raise ValueError(f"sensing must be one of {sorted(SENSING_PRESETS)}, got {str(sensing)[:40]!r}")
    allow_other_world = bool(p(
        "allow_other_world",
        False,
        "Run a bundle trained in another world than the graph's (the world parameter) or with domain "
        "randomisation (its manifest's environment.world, randomisation options, walls_min, snr_max); false: "
        "it is refused",
        True,
    ))
    return dict(
        agent_id=agent_id, namespace=namespace, agents=count("agents", num_agents),
        grid=count("grid", grid), observation=str(observation),
        resolution=number("resolution", resolution),
        sensing=sensing, allow_other_world=allow_other_world, **_declare_world(p), **_declare_runtime(p))


def _declare_world(p) -> dict:
    """Declare the parameters that say the world the team plays and its estimator's prior (``p``
    declares one parameter)."""
    world = check_world(p(
        "world", "grid",
        "The world the team plays: 'grid' (the sensing preset's grid world) or 'radbench' (the field "
        "benchmark's: maps of solid obstructions, the team's estimator the model bundles are trained "
        "with there, sensing realistic; docs/ros-reference.md, 'The benchmark's world')",
        True))
    prior_background = str(p(
        "prior_background", "",
        "World radbench: the team estimator's background prior LOW,HIGH,LEVELS (counts/s, counts/s, "
        "2..64), as medc-radbench --prior-background takes it; empty: the one the policy bundle's "
        "manifest records, else the team model's own (10-50 counts/s at 8 levels)",
        True))
    return dict(world=world, prior_background=prior_background)


def _declare_runtime(p) -> dict:
    """Declare the parameters that say the registry and how a policy runs (``p`` declares one)."""
    bridge_service = p(
        "bridge_service",
        "registry/fetch_bundle",
        "Registry bridge service that fetches and verifies a bundle by content id (a relative name is "
        "taken in the team's namespace: /medc/registry/fetch_bundle by default)",
        True,
    )
    application = p(
        "application", DEFAULT_APPLICATION, "Application a bundle must be trained for", True
    )
    threads = p(
        "torch_threads", 1, "CPU threads for the policy network (1 suits one small net per agent)", True
    )
    runtime = p(
        "policy_runtime", "auto",
        "What runs a bundle's network: auto (onnxruntime where its outputs equal PyTorch's on the dry "
        "run's observations, else PyTorch; the log says which), onnxruntime (a bundle it cannot run is "
        "refused) or torch",
        True,
    )
    if runtime not in RUNTIMES:
        raise ValueError(f"policy_runtime must be one of {', '.join(RUNTIMES)}, got {str(runtime)[:40]!r}")
    max_forward_s = p(
        "policy_max_forward_s",
        MAX_FORWARD_SECONDS,
        "A bundle whose dry run on any of its observations (blank, environment-made, random) takes "
        "longer (seconds) is refused",
        True,
    )
    return dict(
        bridge_service=bridge_service, application=application,
        threads=count("torch_threads", threads, least=1), runtime=runtime,
        max_forward_s=seconds("policy_max_forward_s", max_forward_s))


def declare_agent_parameters(node: Node, agent_id: str | None) -> AgentParameters:
    """Declare every parameter of an agent node on ``node`` and return their values (ValueError for a
    bad sensing preset)."""
    scenario = _declare_scenario(node, agent_id)
    p = lambda *a, **k: declare(node, *a, **k)  # noqa: E731
    stall_timeout_s = seconds("stall_timeout_s", p(
        "stall_timeout_s",
        STALL_TIMEOUT_S,
        "A team step that cannot be decided for this long (seconds) is logged once, with what it "
        "waits for, and published as a diagnostic",
        True,
    ))
    lost_timeout_s = seconds("lost_timeout_s", p(
        "lost_timeout_s", guard.LOST_TIMEOUT_S,
        "A teammate whose pose or reading has not come for this long (seconds) while a step waits "
        "for it is taken out of the team until it is heard again (docs/ros-reference.md, "
        "'A lost UAV'); 0: never",
        True), zero_ok=True)
    session_hold_s = seconds("session_hold_s", p(
        "session_hold_s", guard.SESSION_HOLD_S,
        "Statuses of another driver session are held while the followed one published within this "
        "many seconds (a second graph); after that the new session is followed (a restarted driver)",
        True), zero_ok=True)
    recover_s = seconds("recover_s", p(
        "recover_s", guard.RECOVER_S,
        "A status that jumps ahead is answered once confirmed or re-sent after this many seconds; "
        "statuses below the answered step for this long are followed again",
        True), zero_ok=True)
    edge_tolerance = number("edge_tolerance", p(
        "edge_tolerance", EDGE_TOLERANCE_CELLS,
        "Cells: a pose at most this far outside the map's grid is taken as the nearest edge cell",
        True))
    noise = bool(p(
        "noise",
        False,
        "Whether the team's readings are Poisson counts (the simulator's 'noise'; the realistic "
        "preset always counts them): the gradient controller's flatness test",
        True,
    ))
    rule_out = bool(p(
        "source_ends_episode", True,
        "The driver ends an episode as soon as a UAV finds the source (the simulator's end_on "
        "'source' or 'either'), so a cell the team stood on is not the source; false for a driver "
        "that ends episodes only on the team's declaration (a real one: it cannot know the source)",
        True))
    endgame_tau = check_endgame_tau(p(
        "endgame_tau", 1.0,
        "The classical endgame: once the team's posterior holds at least this on one cell and this agent "
        "can reach that cell's success region, it walks a shortest path there instead of the bundle's "
        "move (medc-radbench --endgame); 1.0: never",
        True))
    initial = p(
        "policy", "",
        "Path of the policy bundle (.safetensors) to run, or a classical controller's name "
        f"({', '.join(CONTROLLERS)}; needs agents and grid); set it to swap policies")
    return AgentParameters(
        **scenario, stall_timeout_s=stall_timeout_s, lost_timeout_s=lost_timeout_s,
        session_hold_s=session_hold_s, recover_s=recover_s, edge_tolerance=edge_tolerance, noise=noise,
        rule_out=rule_out, endgame_tau=endgame_tau, policy=str(initial))


@dataclass(frozen=True)
class AgentParameters:
    """An agent node's parameters as declared (:func:`declare_agent_parameters`; their descriptions
    are there and in ``medc-agent --help``)."""

    agent_id: str
    namespace: str
    agents: int
    grid: int
    observation: str
    resolution: float
    sensing: str
    allow_other_world: bool
    world: str
    prior_background: str
    bridge_service: str
    application: str
    threads: int
    runtime: str
    max_forward_s: float
    stall_timeout_s: float
    lost_timeout_s: float
    session_hold_s: float
    recover_s: float
    edge_tolerance: float
    noise: bool
    rule_out: bool
    endgame_tau: float
    policy: str


class MoveOut:
    """This agent's moves on its move topic: each decided step's move, the last one published again
    when the driver re-sends its step, and the inputs of a step the policy failed on kept to decide
    again then."""

    def __init__(self, agent_id: str, sender: str, publish: Callable[[AgentMove], None],
                 stamp: Callable[[], object]) -> None:
        """``sender``: the node's per-run id; ``publish``: sends a move; ``stamp``: the time now, as a
        message stamp."""
        self.agent_id = agent_id
        self.sender = sender
        self.publish_msg = publish
        self.stamp = stamp
        self.last: AgentMove | None = None
        #: (obs, mask, tick) the policy failed on, until a move is published.
        self.unanswered: tuple | None = None
        #: Moves decided (a move published again is not counted).
        self.count = 0

    def publish(self, tick, action: int) -> None:
        """Publish the move ``action`` for ``tick``."""
        self.unanswered = None
        move = AgentMove()
        move.header.stamp = self.stamp()
        move.header.frame_id = contract.MAP_FRAME
        move.agent_id = self.agent_id
        move.sender = self.sender
        move.episode, move.step, move.action = tick.episode, tick.step, int(action)
        self.last = move
        self.count += 1
        self.publish_msg(move)

    def again(self, tick) -> tuple | None:
        """``tick`` is re-sent by the driver (it has not got every move for it: ours may have been
        lost, or the policy failed on it): publish its move again, or return the inputs the policy
        failed on to decide again (None when there are none)."""
        last = self.last
        if last is not None and (last.episode, last.step) == (tick.episode, tick.step):
            self.publish_msg(last)
            return None
        if self.unanswered is not None and self.unanswered[2] == tick:
            return self.unanswered
        return None


class Decider:
    """This agent's move on an observation: the slot's classical controller on the team state, else
    the classical endgame's where it plans (medc_agents.bench_team), else its policy. A policy failing
    on one observation must not take the node down: it is logged and the observation kept on
    ``moves`` (MoveOut.unanswered) to decide again when the step is re-sent."""

    def __init__(self, slot, observer, moves: MoveOut, noise: bool, logger, endgame_tau: float = 1.0) -> None:
        """``slot``: the agent's PolicySlot; ``observer``: its TeamObserver; ``noise``: readings are
        Poisson counts (the gradient controller's flatness test); ``endgame_tau``: the posterior mass
        on its mode that starts the endgame of a bundle's team (1.0: never)."""
        self.slot = slot
        self.observer = observer
        self.moves = moves
        self.noise = noise
        self.logger = logger
        self.endgame_tau = endgame_tau
        #: Moves the endgame decided.
        self.planned = 0

    def endgame(self, mask) -> int | None:
        """The endgame's move on the step just observed, when a bundle runs and the endgame plans it."""
        if self.endgame_tau >= 1.0 or self.slot.controller is not None:
            return None
        try:
            move = endgame_move(self.observer, self.endgame_tau, mask)
        except Exception as exc:  # the planner must never cost the team its move: the policy decides
            self.logger.error(f"endgame not planned: {type(exc).__name__}: {printable(str(exc), 200)}")
            return None
        self.planned += move is not None
        return move

    def decide(self, obs, mask, tick) -> int | None:
        """The move for ``tick``, or None when the policy failed on it."""
        try:
            if self.slot.controller is not None:
                return controller_move(self.slot.controller, self.observer, mask, self.noise)
            planned = self.endgame(mask)
            if planned is not None:
                return planned
            return self.slot.act(obs, mask)
        except Exception as exc:
            self.logger.error(f"policy failed on episode {tick.episode} step {tick.step}: "
                              f"{refusal_reason(PolicyRejected(exc))}")
            self.moves.unanswered = (obs, mask, tick)
            return None


class AgentNode(Node):
    """One agent of the team, made of the parts the module docstring lists."""

    def __init__(self, node_name: str | None = None, agent_id: str | None = None,
                 feed: TeamFeed | None = None, **kwargs) -> None:
        """``feed``: a :class:`TeamFeed` shared by this process's agent nodes that hands this node the
        team's messages (None: it subscribes to them itself). Raises ValueError for a bad parameter,
        PolicyRejected when the policy cannot run (:meth:`PolicySwaps.start`)."""
        kwargs.setdefault("namespace", contract.DEFAULT_NAMESPACE)
        super().__init__(node_name or default_node_name(agent_id), **kwargs)
        prm = declare_agent_parameters(self, agent_id)
        self.agent_id = prm.agent_id
        #: The team's namespace (fully qualified) and the one names are built with (None: relative).
        self.namespace_, self.names_ns = contract.team_namespace(self.get_namespace(), prm.namespace)
        self.bridge_service = contract.team_name(self.names_ns, prm.bridge_service)
        self.stall_timeout_s = prm.stall_timeout_s
        #: Readings are Poisson counts (what the gradient controller's flatness test assumes).
        self.noise, self.endgame_tau = prm.noise, prm.endgame_tau  # and the classical endgame's tau
        application, initial = prm.application, prm.policy
        observation = explicit_observation = prm.observation
        num_agents, grid, observation = scenario_from_bundle(
            initial, prm.agents, prm.grid, observation, application or None)
        sensing = team_model(prm.world, prm.sensing, prm.prior_background, initial)  # or the benchmark's
        # A one-observation forward pass is far too small to gain from threads; contention costs ms.
        torch.set_num_threads(max(1, prm.threads))
        self.observer = TeamObserver(self.agent_id, num_agents, grid, prm.resolution,
                                     observation or DEFAULT_OBSERVATION, sensing, prm.rule_out,
                                     prm.edge_tolerance, prm.world)
        #: Per-run id of this node, sent with every move (AgentMove.sender).
        self.sender = run_id()
        self.lost_watch = guard.LostWatch(num_agents, self.observer.index, prm.lost_timeout_s)
        self.gate = guard.StatusGate(prm.session_hold_s, prm.recover_s)
        self.reading_check = guard.ReadingCheck(self.observer.sensing, num_agents)
        shape = observation_shape(self.observer.observation, grid)
        self.slot = PolicySlot(shape, NUM_ACTIONS, application or None, prm.max_forward_s,
                               observation=explicit_observation or None,
                               grid=grid if not explicit_observation else None, sensing=sensing,
                               allow_other_world=prm.allow_other_world, runtime=prm.runtime, world=prm.world)
        #: Messages dropped as invalid, by kind (pose, radiation, map, status, policy).
        self.dropped_by: Counter[str] = Counter()
        log, note = self.get_logger(), endgame_words(prm.endgame_tau)
        self.old_statuses = OldStatuses(log, self.dropped_by, OLD_STATUS_SUMMARY_S)
        fetch = BridgeFetch(self.create_client, self.bridge_service, self.agent_id, log)
        self.swaps = PolicySwaps(self.slot, self.observer, log, self.dropped_by, fetch, note)
        #: Called with (source, None) after each swap and (source, reason) after each refusal.
        self.swap_listeners = self.swaps.listeners

        self.swaps.start(str(initial))
        self.get_logger().info(running_words(self.slot, self.observer, num_agents, grid, prm))
        self.add_on_set_parameters_callback(self.swaps.on_set_parameters)

        self._connect(feed, num_agents)

    def _connect(self, feed: TeamFeed | None, num_agents: int) -> None:
        """Publishers, the watches, subscriptions (the team's messages directly or through ``feed``)
        and timers."""
        ns, log = self.names_ns, self.get_logger()
        self.move_pub = self.create_publisher(
            AgentMove, contract.move_topic(ns, self.agent_id), contract.RELIABLE_QOS
        )
        self.health = Health(self, self.agent_id, self._summary)
        #: Signing of its moves and declarations, checking of the team's messages (medc_common.auth_node);
        #: poses and maps wait until a verified reading or status vouches for them.
        self.auth = declare_auth(self, self.sender, self.health)
        self.signed = SignedInputs(self.auth)
        move_topic = contract.move_topic(self.namespace_, self.agent_id)
        self.moves = MoveOut(self.agent_id, self.sender,
                             lambda m: self.move_pub.publish(self.auth.sign(m, move_topic)),
                             lambda: self.get_clock().now().to_msg())
        self.decider = Decider(self.slot, self.observer, self.moves, self.noise, log, self.endgame_tau)
        self.statuses = StatusIntake(self.gate, self.health, self.dropped_by, self.old_statuses.drop,
                                     self.observer.restart)
        self.readings = ReadingWatch(self.reading_check, self.health)
        #: The ``map`` condition: maps refused or from elsewhere, and the checks of maps taken.
        self.map_faults = MapFaults(self.observer, self.health, log, self.dropped_by)
        # Another process publishing moves as this agent (a duplicate id) is reported here too.
        self.claims = ClaimWatch(self.agent_id, self.sender, self.health)
        self.create_subscription(
            AgentMove, contract.move_topic(ns, self.agent_id),
            lambda m: self.claims.on_move(m) if self.auth.admit(m, move_topic, "move") else None,
            contract.RELIABLE_QOS)
        #: The team's source estimate and declaration (published by one agent: medc_agents.estimate).
        self.estimate = TeamEstimate(self, ns, self.observer.index, self.observer.sensing,
                                     self.lost_watch.timeout_s, num_agents, auth=self.auth)
        self.team = TeamWatch(self.agent_id, self.observer, self.lost_watch, self.estimate, self.health, log,
                              self._maybe_decide)
        self.stalls = StallWatch(self.observer, self.health, self.stall_timeout_s,
                                 lambda: self.slot.current is not None)
        self.drivers = DriverWatch(self.gate, self.health, contract.status_topic(self.namespace_))
        self.notes = NoteLog(self.observer, self.health)
        if feed is None:
            subscribe_team(self, ns, num_agents, [self])
        else:
            feed.add(self, num_agents)
        for topic in (contract.policy_topic(ns, self.agent_id), contract.team_policy_topic(ns)):
            self.create_subscription(String, topic, self.swaps.on_message, contract.LATCHED_QOS)
        if self.stall_timeout_s > 0:
            self.create_timer(min(0.25, self.stall_timeout_s / 4), self._watch)

    def swap_policy(self, source: str) -> str:
        """Validate and run the bundle at ``source``; returns its description (PolicyRejected: refused,
        the previous policy keeps running)."""
        return self.swaps.swap(source)

    @property
    def stalls_reported(self) -> int:
        """Stall reports logged (one per stalled step), for tests and monitoring."""
        return self.stalls.reported

    def _watch(self) -> None:
        """Take silent teammates out; report, once, a team step this agent has not been able to
        decide for stall_timeout_s (and the other watches' due reports)."""
        self.notes.flush()
        self.team.check_lost()
        self.old_statuses.sum_up()
        self.map_faults.check_due()
        self.claims.check()
        self.drivers.check()
        self.stalls.check()

    def _summary(self) -> dict[str, str]:
        o = self.observer
        return {"namespace": self.namespace_, "sender": self.sender, "session": self.gate.session or "",
                "episode": str(o.clock.episode), "step": str(o.clock.step),
                "decisions": str(self.moves.count), "dropped": str(self.dropped),
                "old_statuses": str(self.dropped_by["old status"]),
                "absent": ", ".join(o.ids[j] for j in sorted(o.absent)) or "none",
                "policy": self.slot.current.description if self.slot.current is not None else "none",
                "estimate": ("publishing" if self.estimate.publishing else "standby") if self.estimate.enabled
                else "off", **self.auth.summary()}

    # -- team state ----------------------------------------------------------------------------
    def on_pose(self, agent_id: str, msg: PoseStamped) -> None:
        msg = self.signed.pose(agent_id, msg)  # signing: once the signed reading of its step vouches
        if msg is not None:
            self._take_pose(agent_id, msg)

    def _take_pose(self, agent_id: str, msg: PoseStamped) -> None:
        try:
            self.observer.add_pose(agent_id, msg)
        except ValueError as exc:
            self._drop("pose", exc)
            return
        self.team.heard("pose", agent_id)
        self._maybe_decide()

    def on_reading(self, agent_id: str, msg: RadiationReading) -> None:
        if not self.auth.admit(msg, contract.radiation_topic(self.namespace_, agent_id), "reading"):
            return
        pose = self.signed.pose_of(agent_id, msg)
        if pose is not None:
            self._take_pose(agent_id, pose)
        try:
            self.observer.add_reading(agent_id, msg)
        except ValueError as exc:
            self._drop("radiation", exc)
            return
        self.team.heard("reading", agent_id)
        self.readings.take(self.observer.index_of(agent_id), agent_id, float(msg.value))
        self._maybe_decide()

    def on_map(self, msg: OccupancyGrid) -> None:
        msg = self.signed.map(msg)  # signing: once a signed status names its digest
        if msg is not None:
            self._take_map(msg)

    def _take_map(self, msg: OccupancyGrid) -> None:
        if self.map_faults.take(msg):
            self.notes.flush()
            self._maybe_decide()

    def _drop(self, what: str, exc: Exception) -> None:
        self.dropped_by[what] += 1
        self.get_logger().warning(f"dropped {what} message: {exc}")

    def on_status(self, msg: EpisodeStatus, defer: bool = False):
        """Take an episode status; decide if everything for the step is there.

        ``defer``: instead of deciding, return ``(obs, mask, tick)`` for the caller to decide
        (a TeamFeed batches the team's forward passes) and to finish with :meth:`publish_move`.
        """
        o = self.observer
        if not self.auth.admit(msg, contract.status_topic(self.namespace_), "status"):
            return None
        grid = self.signed.map_of(msg)
        if grid is not None:
            self._take_map(grid)
        if list(msg.agent_ids) != o.ids:
            listed = list(msg.agent_ids)[:8]
            self._drop("status", ValueError(f"status lists agents {listed}, this team is {o.ids}"))
            return None
        if not self.statuses.admit(msg, o.clock):
            return None
        try:
            tick = self.observer.add_status(msg)
        except ValueError as exc:
            self._drop("status", exc)
            return
        self.team.readmit()
        if tick is not None and self.observer.answered_tick(tick):
            unanswered = self.moves.again(tick)
            if unanswered is not None:
                self._decide(*unanswered)
            return None
        if defer:
            if not self._ready():
                return None
            return self.observer.observe()
        self._maybe_decide()
        return None

    def _ready(self) -> bool:
        """Whether the pending step can be decided now (the poses the observer dropped on the way,
        held before their map was known, are logged and counted)."""
        ready = self.slot.current is not None and self.observer.ready()
        drops, self.observer.late_drops[:] = list(self.observer.late_drops), []
        for reason in drops:
            self._drop("pose", ValueError(reason))
        return ready

    def _maybe_decide(self) -> None:
        if not self._ready():
            return
        self._decide(*self.observer.observe())

    def _decide(self, obs, mask, tick) -> None:
        action = self.decider.decide(obs, mask, tick)
        if action is not None:
            self.publish_move(tick, action)

    def publish_move(self, tick, action: int) -> None:
        """Publish this agent's move for ``tick`` (and remember it for re-sent steps)."""
        self.stalls.over(tick)
        self.map_faults.decided(tick)
        self.notes.flush()
        try:  # the estimate goes out before the move: a driver ending on the declaration sees it first
            self.estimate.on_step(self.observer, tick)
        except Exception as exc:  # never let the estimate cost the team its move
            self.get_logger().error(f"team estimate not published for episode {tick.episode} step "
                                    f"{tick.step}: {type(exc).__name__}: {printable(str(exc), 300)}")
        try:
            self.team.report_silent(tick)
        except Exception as exc:  # a report must never cost the team its move
            self.get_logger().error(f"silent teammates not checked: {type(exc).__name__}")
        self.moves.publish(tick, action)

    @property
    def dropped(self) -> int:
        """Messages dropped as invalid, in all."""
        return sum(self.dropped_by.values())


def subscribe_team(node: Node, namespace: str | None, num_agents: int, agents: list[AgentNode]) -> None:
    """Subscribe ``node`` to the team's poses, readings, map and status, for ``agents`` (names under
    ``namespace``; None: relative to the node's namespace).

    Each message is handed to every agent in ``agents`` (the list may grow later).
    """
    for a in contract.agent_ids(num_agents):
        node.create_subscription(
            PoseStamped,
            contract.pose_topic(namespace, a),
            lambda m, a=a: [agent.on_pose(a, m) for agent in agents],
            contract.SENSOR_QOS,
        )
        node.create_subscription(
            RadiationReading,
            contract.radiation_topic(namespace, a),
            lambda m, a=a: [agent.on_reading(a, m) for agent in agents],
            contract.SENSOR_QOS,
        )
    node.create_subscription(
        OccupancyGrid,
        contract.map_topic(namespace),
        lambda m: [agent.on_map(m) for agent in agents],
        contract.MAP_READER_QOS,
    )
    node.create_subscription(
        EpisodeStatus,
        contract.status_topic(namespace),
        lambda m: decide_together(agents, m) if len(agents) > 1 else [agent.on_status(m) for agent in agents],
        contract.RELIABLE_QOS,
    )


def decide_together(agents: list[AgentNode], msg: EpisodeStatus) -> None:
    """Hand ``msg`` to every agent; those ready to decide and running the same bundle object in the
    same runtime decide in one batched forward pass (the same greedy choice as one by one); an agent
    running a controller decides on its own."""
    groups: dict[int, list] = {}
    for agent in agents:
        prepared = agent.on_status(msg, defer=True)
        if prepared is None:
            continue
        if agent.slot.controller is not None:  # no network to batch: it decides from its team state
            agent._decide(*prepared)
            continue
        planned = agent.decider.endgame(prepared[1])
        if planned is not None:  # the endgame plans this agent's move: no forward pass
            agent.publish_move(prepared[2], planned)
            continue
        groups.setdefault(id(agent.slot.decider), []).append((agent, *prepared))
    for members in groups.values():
        decider = members[0][0].slot.decider
        obs = torch.stack([m[1] for m in members])
        mask = torch.stack([m[2] for m in members])
        try:
            with torch.no_grad():
                actions = decider.act(obs, mask).tolist()
        except Exception:
            # Fall back to one by one: each agent logs and keeps its own failure.
            for agent, o, mk, tick in members:
                agent._decide(o, mk, tick)
            continue
        for (agent, _, _, tick), action in zip(members, actions):
            agent.publish_move(tick, action)


class TeamFeed(Node):
    """One set of team subscriptions shared by the agent nodes of one process.

    With N agents in one process, each of their own subscriptions would receive and deserialize
    every team message: N x (2N + 2) deliveries per step. Sharing them makes it 2N + 2; each agent
    still checks every message itself and keeps its own memory, policy and move topic.
    """

    def __init__(self, namespace: str, num_agents: int, node_name: str = "medc_team_feed", **kwargs) -> None:
        """``namespace``: the team's (the node is created in it; its subscriptions are relative)."""
        super().__init__(node_name, namespace=contract.check_namespace(namespace), **kwargs)
        #: The team's namespace, fully qualified (the agents fed must be in the same one).
        self.namespace = self.get_namespace()
        self.num_agents = num_agents
        self.agents: list[AgentNode] = []
        subscribe_team(self, contract.RELATIVE, num_agents, self.agents)

    def add(self, agent: AgentNode, num_agents: int) -> None:
        """Feed ``agent`` (one of ``num_agents`` in its namespace; ValueError for another team)."""
        if (self.namespace, self.num_agents) != (agent.namespace_, num_agents):
            raise ValueError(
                f"team feed serves {self.num_agents} agents on {self.namespace}, "
                f"agent {agent.agent_id} is one of {num_agents} on {agent.namespace_}"
            )
        self.agents.append(agent)
