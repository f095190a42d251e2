"""The team's source estimate on the graph: where the team believes the source is, and its declaration.

Every agent keeps the team's posterior over the source cell (``TeamObserver.memory``, the training
environment's :class:`~medc_training.envs.tl_observation.TeamMemory`); all agents hold the same one.
One agent publishes it for the team: the lowest-numbered live one (:class:`EstimateRole`), agent_0
while it lives; an agent with ``publish_estimate`` false never does. Every agent keeps the estimate
of its latest steps, so the agent the role comes to first publishes those of the steps since the
last move of the teammates it takes over from. After each team step it has decided, before its
move, it publishes (topics: ``medc_common.contract``):

- ``<ns>/team/source_estimate`` (geometry_msgs/PoseWithCovarianceStamped, frame ``map``, stamp =
  the step's): the posterior mean of the source's position and its covariance (x, y block; the
  spread of the posterior over cell centres plus the uniform spread within a cell, r²/12 per axis;
  z and the orientation are not estimated: 0);
- ``<ns>/team/source_posterior`` (nav_msgs/OccupancyGrid on the walls map's grid, same
  ``info``): the posterior as a heat map, 100 = the most probable cell, round(100 · p / p_max),
  at most ``estimate_map_rate_hz`` times a second (0 = never);
- ``<ns>/team/source_declared`` (medc_interfaces/SourceDeclaration): once per episode, when the
  posterior mass within ``declare_radius`` cells of the most probable cell reaches
  ``declare_threshold`` (:func:`medc_training.envs.tl_estimate.declare`).

The pure conversions (:func:`estimate_in_map`, :func:`heat_map_data`) and :class:`EstimateRole`
take no ROS objects.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

import torch
from medc_common import contract
from medc_common.contract import GridGeometry, cell_to_ij
from medc_common.params import declare

#: Parameter defaults (docs/ros-reference.md, "The team's source estimate").
DEFAULT_MAP_RATE_HZ = 1.0
#: A teammate never heard from is silent this many times ``lost_timeout_s`` after an agent's first
#: step (the simulator likewise gives an agent that never moved 5 x its move timeout).
NEVER_HEARD_FACTOR = 5.0
#: Steps whose estimate an agent keeps to publish when the role comes to it.
RECENT_STEPS = 8


def estimate_in_map(mean_rc: tuple[float, float], cov_rc, geometry: GridGeometry
                    ) -> tuple[tuple[float, float], list[list[float]]]:
    """((x, y), 2×2 covariance) in the map frame of a posterior mean (row, col) and covariance
    [[rr, rc], [cr, cc]] in cells (over cell centres): the grid frame's (i, j) = (col, H - 1 - row),
    the spread within a cell (1/12 cell² per axis) added, scaled by the resolution and rotated by
    the map origin's yaw."""
    row, col = float(mean_rc[0]), float(mean_rc[1])
    gx = (col + 0.5) * geometry.resolution
    gy = (geometry.height - 1 - row + 0.5) * geometry.resolution
    c, s = math.cos(geometry.origin_yaw), math.sin(geometry.origin_yaw)
    x = geometry.origin_x + c * gx - s * gy
    y = geometry.origin_y + s * gx + c * gy
    # (i, j) = (col, H-1-row): var_i = var_col, var_j = var_row, cov_ij = -cov_rowcol.
    r2 = geometry.resolution ** 2
    vi = (float(cov_rc[1][1]) + 1.0 / 12.0) * r2
    vj = (float(cov_rc[0][0]) + 1.0 / 12.0) * r2
    cij = -float(cov_rc[0][1]) * r2
    # R C R^T with R the yaw rotation.
    xx = c * c * vi - 2 * c * s * cij + s * s * vj
    yy = s * s * vi + 2 * c * s * cij + c * c * vj
    xy = c * s * (vi - vj) + (c * c - s * s) * cij
    return (x, y), [[xx, xy], [xy, yy]]


def heat_map_data(posterior: torch.Tensor, grid: int) -> list[int]:
    """OccupancyGrid ``data`` (message row j = environment row H - 1 - j) of a posterior float [G²]
    (row-major environment cells): round(100 · p / p_max), 0..100."""
    p = posterior.reshape(grid, grid).double()
    top = float(p.max())
    scaled = torch.zeros_like(p) if top <= 0 else torch.round(p * (100.0 / top))
    return scaled.flip(0).to(torch.int8).flatten().tolist()


class EstimateRole:
    """Which teammates have stopped moving, and whether agent ``own`` publishes the team's estimate.

    Every agent follows its teammates' moves (:meth:`moved`) and the steps it decides itself
    (:meth:`decided`). Teammate ``j`` is *silent* at the step this agent decides when its latest move
    is neither for that step nor for the step this agent decided before it (the driver collects every
    move of a step before it publishes the next, so a teammate with no move for the previous step was
    stepped on without: taken out, "A lost UAV"), and no move came from it for ``timeout_s`` (a move
    still on its way is for the previous step, and comes within milliseconds); a teammate never heard
    from is silent :data:`NEVER_HEARD_FACTOR` x ``timeout_s`` after this agent's first step (its
    process may still be starting, or its move topic not yet matched). Across an episode's end the previous
    step is the last step of the episode before, so the first steps of an episode follow the same rule.

    A silent teammate moves again (:meth:`moved`) by a move from the sender it moved with before
    (its own process, heard again), or by moves for two steps from one new sender (a restarted
    process); moves that each come under a new sender (a ghost answering for it) never bring it back.

    Agent ``own`` holds the role (publishes the estimate) when every agent numbered below it is
    silent; agent 0 always holds it; when a lower-numbered agent moves again, it hands it back.
    ``timeout_s`` <= 0 (the agent's ``lost_timeout_s`` 0: no teammate is ever taken out): nobody is
    ever silent and the role never passes on."""

    def __init__(self, own: int, timeout_s: float, clock: Callable[[], float] = time.monotonic,
                 num_agents: int = 0) -> None:
        """``num_agents``: the team's size (0: only the agents numbered below ``own`` are followed)."""
        self.own = own
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self.num_agents = max(int(num_agents), own + 1)
        #: Per teammate: ((episode, step) of its latest move, when it came).
        self.last: dict[int, tuple[tuple[int, int], float]] = {}
        self._since: float | None = None
        #: The steps this agent decided: the latest and the one before it.
        self.current: tuple[int, int] | None = None
        self.previous: tuple[int, int] | None = None
        #: Teammates found silent, until they move again; the sender each moved with before.
        self.out: set[int] = set()
        self.senders: dict[int, str] = {}
        self._returning: dict[int, tuple[str, set]] = {}  # a silent teammate's new sender, its steps

    def moved(self, idx: int, episode: int, step: int, sender: str = "") -> None:
        """Teammate ``idx`` moved for (``episode``, ``step``) (``sender``: ``AgentMove.sender``)."""
        if idx == self.own or not 0 <= idx < self.num_agents:
            return
        tick, sender = (int(episode), int(step)), str(sender)
        if idx in self.out:
            if not self._returns(idx, tick, sender):
                return
            self.out.discard(idx)
            self._returning.pop(idx, None)
        # The latest, not the highest: one forged far-ahead step holds nothing.
        self.last[idx] = (tick, self.clock())
        self.senders[idx] = sender

    def _returns(self, idx: int, tick: tuple[int, int], sender: str) -> bool:
        """Whether a move of silent teammate ``idx`` brings it back (class docstring)."""
        if sender == self.senders.get(idx):
            return True
        seen = self._returning.get(idx)
        if seen is None or seen[0] != sender:
            self._returning[idx] = (sender, {tick})
            return False
        seen[1].add(tick)
        return len(seen[1]) >= 2

    def decided(self, episode: int, step: int) -> None:
        """This agent decides (``episode``, ``step``) (again: nothing changes)."""
        tick = (int(episode), int(step))
        if self._since is None:
            self._since = self.clock()
        if tick != self.current:
            self.previous, self.current = self.current, tick

    def gone(self, idx: int, episode: int, step: int) -> bool:
        """Whether teammate ``idx`` is silent when this agent decides (``episode``, ``step``)."""
        if self.timeout_s <= 0:
            return False
        if idx in self.out:
            return True
        self.decided(episode, step)
        now = self.clock()
        heard = self.last.get(idx)
        if heard is None:  # not started yet, or its move topic not matched yet (discovery takes seconds)
            silent = now - self._since >= NEVER_HEARD_FACTOR * self.timeout_s
        else:
            silent = heard[0] not in (self.current, self.previous) and now - heard[1] >= self.timeout_s
        if silent:
            self.out.add(idx)
        return silent

    def holds(self, episode: int, step: int) -> bool:
        """Whether this agent publishes the estimate of (``episode``, ``step``)."""
        self.decided(episode, step)
        if self.own > 0 and self.timeout_s <= 0:
            return False
        return all(self.gone(j, episode, step) for j in range(self.own))

    def gone_ids(self, episode: int, step: int, below: bool = True) -> list[int]:
        """The silent teammates at (``episode``, ``step``); ``below``: only those below this agent."""
        team = range(self.own) if below else (j for j in range(self.num_agents) if j != self.own)
        return [j for j in team if self.gone(j, episode, step)]


class TeamEstimate:
    """The agent node's publisher of the team's estimate and declaration (module docstring)."""

    def __init__(self, node, namespace: str, agent_index: int, sensing, takeover_s: float = 1.5,
                 num_agents: int = 0, auth=None) -> None:
        """Declare the parameters on ``node``, follow the moves of every teammate (:class:`EstimateRole`,
        ``takeover_s``; ``num_agents``: the team's size) and, when it may publish, create its publishers.
        ``auth``: the node's medc_common.auth_node.NodeAuth (None: the open mode): a teammate's move
        counts only when it verifies, and declarations are signed.

        Raises:
            ValueError: a declaration radius or threshold out of range, a negative rate.
        """
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from medc_interfaces.msg import SourceDeclaration
        from medc_training.envs.tl_estimate import DEFAULT_THRESHOLD, check_rule
        from nav_msgs.msg import OccupancyGrid

        p = lambda *a, **k: declare(node, *a, **k)  # noqa: E731
        self.node = node
        self.auth = auth
        #: The team's namespace, fully qualified (the topics signatures name).
        self.team_ns = node.namespace_
        self.enabled = bool(p(
            "publish_estimate", True,
            "Publish the team's source estimate, posterior heat map and declaration when this agent is "
            "the lowest-numbered live one (agent_0 while it lives; every agent holds the same "
            "posterior); false: never", True))
        radius = float(p(
            "declare_radius", -1.0,
            "Declaration rule: radius in cells around the most probable cell (Euclidean, between cell "
            "centres); -1 = the sensing preset's success radius (paper-simple 0, realistic 1.1)", True))
        threshold = float(p(
            "declare_threshold", DEFAULT_THRESHOLD,
            "Declaration rule: the posterior mass within declare_radius that declares the source "
            "localised (0 < t <= 1)", True))
        self.radius, self.threshold = check_rule(sensing.success_radius if radius < 0 else radius, threshold)
        rate = float(p("estimate_map_rate_hz", DEFAULT_MAP_RATE_HZ,
                       "Most posterior heat maps published per second (0 = none)", True))
        if not (rate >= 0 and math.isfinite(rate)):
            raise ValueError(f"estimate_map_rate_hz must be >= 0, got {rate!r}")
        self.map_period = 1.0 / rate if rate > 0 else None
        self._last_map_at = -math.inf
        self._declared_for: tuple[int, int] | None = None
        #: Declarations published (tests, monitoring).
        self.declarations = 0
        self.last_estimate: tuple[float, float] | None = None
        #: Estimates published, the ones of steps taken over included (tests, monitoring).
        self.published = 0
        self.role = EstimateRole(agent_index, takeover_s, num_agents=num_agents)
        #: The estimate of each of the latest steps this agent decided: (tick, estimate message),
        #: published when the role comes to it for the steps no teammate published.
        self.recent: deque[tuple[object, object]] = deque(maxlen=RECENT_STEPS)
        #: Whether this agent holds the role (published the latest step's estimate; agent_0 from the start).
        self.publishing = self.enabled and agent_index == 0
        self._follow_moves(namespace, agent_index, num_agents)
        if not self.enabled:
            return
        self.pose_pub = node.create_publisher(PoseWithCovarianceStamped, contract.estimate_topic(namespace),
                                              contract.ESTIMATE_QOS)
        self.map_pub = node.create_publisher(OccupancyGrid, contract.posterior_topic(namespace),
                                             contract.LATCHED_QOS)
        self.declaration_pub = node.create_publisher(SourceDeclaration, contract.declaration_topic(namespace),
                                                     contract.RELIABLE_QOS)

    def _follow_moves(self, namespace: str, agent_index: int, num_agents: int) -> None:
        from medc_interfaces.msg import AgentMove

        for j in range(max(num_agents, agent_index)):
            if j == agent_index:
                continue
            agent = contract.agent_id(j)

            def on_move(msg, j=j, agent=agent) -> None:
                if self.auth is not None and not self.auth.admit(
                        msg, contract.move_topic(self.team_ns, agent), "move"):
                    return
                if msg.agent_id == agent:  # a move on another agent's topic says nothing of this one
                    self.role.moved(j, msg.episode, msg.step, msg.sender)

            self.node.create_subscription(AgentMove, contract.move_topic(namespace, agent), on_move,
                                          contract.RELIABLE_QOS)

    def silent(self, tick) -> list[int]:
        """The teammates that have stopped moving at ``tick`` (:class:`EstimateRole`)."""
        return self.role.gone_ids(tick.episode, tick.step, below=False)

    def _take_role(self, tick) -> bool:
        """Whether this agent publishes for ``tick``; logs when the role comes to it or leaves it."""
        holds = self.enabled and self.role.holds(tick.episode, tick.step)
        if holds != self.publishing and self.role.own > 0:
            if holds:
                gone = ", ".join(contract.agent_id(j) for j in self.role.gone_ids(tick.episode, tick.step))
                self.node.get_logger().warning(
                    f"{gone} gone: {self.node.agent_id} publishes the team's source estimate from episode "
                    f"{tick.episode} step {tick.step}")
            else:
                self.node.get_logger().info(f"a lower-numbered agent moves again: {self.node.agent_id} "
                                            "stops publishing the team's source estimate")
        taken_over = holds and not self.publishing and self.role.own > 0
        self.publishing = holds
        if taken_over:
            self._publish_missed(tick)
        return holds

    def _publish_missed(self, tick) -> None:
        """The role has just come to this agent at ``tick``: publish the estimates of the steps it
        decided since the latest move of the teammates it takes over from (they published up to that
        step; the steps after it have had no estimate)."""
        heard = {self.role.last[j][0] for j in range(self.role.own) if j in self.role.last}
        missed = []
        for t, msg in reversed(self.recent):
            if (t.episode, t.step) in heard:
                break
            if t != tick:
                missed.append(msg)
        for msg in reversed(missed):
            self.pose_pub.publish(msg)
            self.published += 1

    def on_step(self, observer, tick) -> None:
        """Keep the estimate of the step ``observer`` just observed (``tick``), and, when this agent
        holds the role (:class:`EstimateRole`), publish it, the heat map when due, and the declaration
        when the rule passes for the first time in the episode."""
        if observer.positions is None:
            return
        geometry = observer.map_geometry(tick.map_stamp)
        if geometry is None:
            self.role.decided(tick.episode, tick.step)
            return
        from medc_training.envs.tl_estimate import declare as rule
        from medc_training.envs.tl_estimate import mean_and_covariance

        posterior = observer.memory.posterior()  # [1, G²]
        grid = observer.memory.grid
        stamp = _time_msg(tick.stamp)
        mean, cov = mean_and_covariance(posterior, grid)
        (x, y), c = estimate_in_map(mean[0].tolist(), cov[0].tolist(), geometry)
        self.last_estimate = (x, y)
        pose = self._pose_msg(stamp, x, y, c)
        if not self._take_role(tick):
            self.recent.append((tick, pose))
            return
        self.recent.append((tick, pose))
        self.pose_pub.publish(pose)
        self.published += 1
        now = time.monotonic()
        if self.map_period is not None and now - self._last_map_at >= self.map_period:
            self._last_map_at = now
            self.map_pub.publish(self._map_msg(stamp, tick.map_stamp, geometry, posterior[0], grid))
        episode = (tick.episode, tick.map_stamp)
        if self._declared_for == episode:
            return
        verdict = rule(posterior, grid, self.radius, self.threshold)
        if bool(verdict.declared[0]):
            self._declared_for = episode
            self.declarations += 1
            declaration = self._declaration_msg(stamp, tick, geometry, verdict)
            if self.auth is not None:
                self.auth.sign(declaration, contract.declaration_topic(self.team_ns))
            self.declaration_pub.publish(declaration)
            row, col = (int(v) for v in verdict.cell[0])
            self.node.get_logger().info(
                f"source declared: episode {tick.episode} step {tick.step}, cell (row {row}, col {col}), "
                f"posterior mass {float(verdict.mass[0]):.3f} within {self.radius:g} cells")

    def _pose_msg(self, stamp, x: float, y: float, c):
        from geometry_msgs.msg import PoseWithCovarianceStamped

        msg = PoseWithCovarianceStamped()
        msg.header.stamp = stamp
        msg.header.frame_id = contract.MAP_FRAME
        msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
        msg.pose.pose.orientation.w = 1.0
        cov = [0.0] * 36
        cov[0], cov[1], cov[6], cov[7] = c[0][0], c[0][1], c[1][0], c[1][1]
        msg.pose.covariance = cov
        return msg

    def _map_msg(self, stamp, map_stamp: int, geometry: GridGeometry, posterior: torch.Tensor, grid: int):
        from nav_msgs.msg import OccupancyGrid

        msg = OccupancyGrid()
        msg.header.stamp = stamp
        msg.header.frame_id = contract.MAP_FRAME
        msg.info.map_load_time = _time_msg(map_stamp)
        msg.info.resolution = float(geometry.resolution)
        msg.info.width, msg.info.height = grid, grid
        msg.info.origin.position.x, msg.info.origin.position.y = geometry.origin_x, geometry.origin_y
        msg.info.origin.orientation.z = math.sin(geometry.origin_yaw / 2)
        msg.info.origin.orientation.w = math.cos(geometry.origin_yaw / 2)
        msg.data = heat_map_data(posterior, grid)
        return msg

    def _declaration_msg(self, stamp, tick, geometry: GridGeometry, verdict):
        from medc_interfaces.msg import SourceDeclaration

        row, col = (int(v) for v in verdict.cell[0])
        i, j = cell_to_ij(row, col, geometry.height)
        x, y = geometry.cell_to_xy(row, col)
        msg = SourceDeclaration()
        msg.header.stamp = stamp
        msg.header.frame_id = contract.MAP_FRAME
        msg.agent_id = self.node.agent_id
        msg.episode, msg.step = tick.episode, tick.step
        msg.map_stamp = _time_msg(tick.map_stamp)
        msg.cell_i, msg.cell_j = i, j
        msg.position.x, msg.position.y = x, y
        msg.mass = float(verdict.mass[0])
        msg.radius_cells = self.radius
        msg.radius_m = self.radius * geometry.resolution
        msg.threshold = self.threshold
        return msg


def _time_msg(key: int):
    """builtin_interfaces/Time of a stamp key (integer nanoseconds)."""
    from builtin_interfaces.msg import Time

    return Time(sec=key // 1_000_000_000, nanosec=key % 1_000_000_000)
