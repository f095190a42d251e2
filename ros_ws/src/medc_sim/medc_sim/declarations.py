"""The team's source declarations to the simulator (``end_on`` 'declaration' or 'either'): the one
that names the episode in play, comes from a member of the team and cannot be told from a stranger's
ends the episode; the others are dropped, a refused one reported on /diagnostics (part
``declarations``) until one is taken.

Owned by :class:`medc_sim.simulator.SimNode` and built from what it reads (the core, the move book, the
episode's map stamp, the graph's publishers) and callables that end the episode and count a drop;
the cell rule is :func:`medc_sim.episode_end.declared_cell`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
from medc_common import contract
from medc_training.untrusted import printable

from medc_sim.episode_end import declared_cell


class Declarations:
    """The declaration subscription of a simulator node, and its verdicts."""

    def __init__(self, node, names_ns: str | None, namespace: str, ids: list[str], core, book, health, *,
                 running: Callable[[], bool], map_stamp: Callable[[], Any],
                 finish: Callable[[Any], None], drop: Callable[[], None], auth=None) -> None:
        """Subscribe ``node`` (the simulator's; its graph tells who publishes) to the team's
        declaration topic under ``names_ns``; ``namespace``: the team's, fully qualified; ``core``,
        ``book``: the simulator's SimCore and MoveBook; ``running``: whether it has started and not
        finished; ``map_stamp``: the episode's map stamp; ``finish``: ends the episode with its
        EpisodeResult; ``drop``: counts a dropped message; ``auth``: the node's
        medc_common.auth_node.NodeAuth (None: the open mode)."""
        from medc_interfaces.msg import SourceDeclaration

        self.ids = ids
        self.core = core
        self.book = book
        self.health = health
        self.logger = node.get_logger()
        self.publishers_of = node.get_publishers_info_by_topic
        self.running = running
        self.map_stamp = map_stamp
        self.finish = finish
        self.drop = drop
        self.namespace = namespace
        self.auth = auth
        #: The declaration topic, fully qualified (its publishers are looked up in the graph).
        self.topic = contract.declaration_topic(namespace)
        #: Declarations that ended an episode, and those refused as not the team's.
        self.taken = 0
        self.refused = 0
        node.create_subscription(SourceDeclaration, contract.declaration_topic(names_ns),
                                 self.on_declaration, contract.RELIABLE_QOS)

    def refusal(self, msg) -> str | None:
        """Why a declaration is not the team's, or None. It must name an agent of the team that is
        not taken out, and every node that publishes declarations must be one that publishes an
        agent's moves (a message does not say which node sent it: while another node publishes
        declarations, none can be told from its own). Under a mission key the signature, checked on
        arrival, takes the place of that graph check."""
        ids = self.ids
        agent = str(msg.agent_id)
        if agent not in ids:
            return (f"it names {printable(agent, 40)!r}, not an agent of this team "
                    f"({', '.join(ids)}); a declaration counts only from a team member")
        if ids.index(agent) in self.book.lost:
            return (f"{agent} is out of the team (no move within move_timeout_s); it counts when it moves "
                    "again")
        if self.auth is not None and self.auth.enabled:
            return None  # signed under the mission key (checked on arrival): a key holder's, whoever runs it
        publishers_of = self.publishers_of
        try:
            movers = {(i.node_namespace, i.node_name) for a in ids
                      for i in publishers_of(contract.move_topic(self.namespace, a))}
            publishers = {(i.node_namespace, i.node_name) for i in publishers_of(self.topic)}
        except Exception as exc:  # the graph unreadable (shutting down): nothing to tell it from
            return f"the publishers of {self.topic} could not be read ({type(exc).__name__})"
        strangers = sorted(publishers - movers)
        if strangers:
            names = ", ".join(printable(f"{ns.rstrip('/')}/{name}", 80) for ns, name in strangers[:4])
            return (f"{len(strangers)} node(s) that move no agent publish on {self.topic} ({names}): a "
                    "declaration cannot be told from theirs; refused until they are gone")
        return None

    def on_declaration(self, msg) -> None:
        """End the episode on the team's declaration."""
        if not self.running():
            return
        if self.auth is not None and not self.auth.admit(msg, self.topic, "declaration"):
            self.drop()
            self.refused += 1
            return
        core, log, map_stamp = self.core, self.logger, self.map_stamp()
        if int(msg.episode) < core.episode:
            return  # the episode has ended already (e.g. a UAV found the source under 'either')
        if int(msg.episode) != core.episode or (msg.map_stamp.sec, msg.map_stamp.nanosec) != (
                map_stamp.sec, map_stamp.nanosec) or int(msg.step) > core.step:
            log.warning(
                f"dropped declaration for episode {msg.episode} step {msg.step}: the simulator is at episode "
                f"{core.episode} step {core.step} (its map_stamp must be this episode's map)")
            return
        try:
            cell = declared_cell(msg.cell_i, msg.cell_j, core.config.grid)
            refusal = self.refusal(msg)
        except ValueError as exc:
            self.drop()
            log.warning(f"dropped declaration: {exc}")
            return
        if refusal:
            self.drop()
            self.refused += 1
            self.health.set("declarations", DiagnosticStatus.WARN, f"declaration refused: {refusal}")
            return
        if self.health.level("declarations") != DiagnosticStatus.OK:
            self.health.set("declarations", DiagnosticStatus.OK, f"declaration of {msg.agent_id} taken")
        self.taken += 1
        finished = core.end_by_declaration(cell)
        log.info(
            f"episode {finished.episode} ended by the team's declaration at step {finished.length} "
            f"(declared at step {msg.step}, posterior mass {msg.mass:.3f}): {finished.error:.2f} cells "
            f"from the source, {'found' if finished.success else 'wrong cell'}")
        self.finish(finished)
