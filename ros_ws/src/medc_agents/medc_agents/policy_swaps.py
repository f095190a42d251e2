"""An agent node's policy swaps at run time: by parameter, by topic (a path or a content id fetched
through the registry bridge), and refusals that keep the running policy.

:class:`PolicySwaps` is owned by :class:`medc_agents.node.AgentNode` and built from the slot it
swaps, the observer that follows the slot's observation, a logger and a fetch callable (a
:class:`BridgeFetch`); the slot itself (validation, dry run, cache) is
:class:`medc_agents.policy_slot.PolicySlot`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

from medc_interfaces.srv import FetchBundle
from medc_training.untrusted import printable
from rcl_interfaces.msg import SetParametersResult
from std_msgs.msg import String

from medc_agents.policy_slot import PolicyRejected, looks_like_cid, shown, strip_cid


def refusal_reason(exc: BaseException) -> str:
    """What a refusal says: the PolicyRejected text, or just the type of an unexpected error;
    printable ASCII only and bounded, as it goes to the log, /rosout and the caller."""
    text = str(exc) if isinstance(exc, PolicyRejected) else f"could not be loaded ({type(exc).__name__})"
    return printable(text, 2000)


class BridgeFetch:
    """Asks the registry bridge for a bundle by content id on behalf of one agent; the bridge
    verifies it and publishes its local path on the agent's policy topic."""

    def __init__(self, create_client: Callable[[type, str], Any], service: str, agent_id: str,
                 logger) -> None:
        """``create_client``: the node's (called with FetchBundle and ``service`` on first use)."""
        self.create_client = create_client
        self.service = service
        self.agent_id = agent_id
        self.logger = logger
        self.client: Any = None

    def __call__(self, cid: str) -> None:
        """Ask for ``cid``. Raises PolicyRejected when the bridge's service is not running."""
        if self.client is None:
            self.client = self.create_client(FetchBundle, self.service)
        if not self.client.service_is_ready():
            raise PolicyRejected(f"registry bridge service {self.service} is not running")
        self.client.call_async(FetchBundle.Request(cid=cid, agent_ids=[self.agent_id]))
        self.logger.info(f"asked the registry bridge for bundle {cid}")


class PolicySwaps:
    """The policy swaps of one agent: each source is validated by ``slot``; the observer then takes
    the slot's observation; a refusal is logged and the running policy keeps running."""

    def __init__(self, slot, observer, logger, dropped_by: Counter, fetch: Callable[[str], None],
                 note: str = "") -> None:
        """``slot``: the agent's PolicySlot; ``observer``: its TeamObserver; ``dropped_by``: its count
        of dropped messages by kind (a refused policy message adds 'policy'); ``fetch``: asks for a
        bundle by content id (raises PolicyRejected when it cannot); ``note``: what the log line of
        a swap adds (the classical endgame, when it is on)."""
        self.slot = slot
        self.observer = observer
        self.logger = logger
        self.dropped_by = dropped_by
        self.fetch = fetch
        self.note = note
        #: Called with (source, None) after each swap and (source, reason) after each refusal.
        self.listeners: list[Callable[[str, str | None], None]] = []

    def start(self, source: str) -> None:
        """Run the first policy, ``source``; the observer takes its observation. Raises
        PolicyRejected with the reason when it cannot run: the node refuses to start rather than
        idle without a policy."""
        try:
            self.slot.swap(source)
        except Exception as exc:  # PolicyRejected, or anything else: refuse to start, with the reason
            why = refusal_reason(exc)
            raise PolicyRejected(f"policy {shown(source)} refused, not starting: {why}") from None
        self.observer.use_observation(self.slot.observation)

    def swap(self, source: str) -> str:
        """Validate and run the bundle at ``source``; returns its description.

        Raises:
            PolicyRejected: refused; the previous policy keeps running.
        """
        loaded = self.slot.swap(source)
        self.observer.use_observation(self.slot.observation)
        self.logger.info(f"now running policy {loaded.description} "
                         f"(observation {self.observer.observation.name}){self.slot.runs_in()}{self.note}")
        for listener in self.listeners:
            listener(source, None)
        return loaded.description

    def refused(self, source: str, exc: Exception) -> None:
        why = refusal_reason(exc)
        self.logger.error(f"policy {shown(source)} refused, keeping the running one: {why}")
        for listener in self.listeners:
            try:
                listener(source, why)
            except Exception as err:  # a listener's bug must not turn a refusal into a crash
                self.logger.error(f"policy swap listener failed: {type(err).__name__}")

    def on_set_parameters(self, params) -> SetParametersResult:
        """The node's parameter callback: a new ``policy`` value is swapped in, or refused."""
        for param in params:
            if param.name != "policy":
                continue
            try:
                self.swap(str(param.value))
            except Exception as exc:  # PolicyRejected, or anything at all: refuse, keep running
                self.refused(str(param.value), exc)
                return SetParametersResult(successful=False, reason=refusal_reason(exc))
        return SetParametersResult(successful=True)

    def on_message(self, msg: String) -> None:
        """A message on a policy topic: a bundle path, a controller's name or a content id."""
        source = ""
        try:
            source = msg.data.strip()
            if looks_like_cid(source):
                self._fetch(strip_cid(source))
                return
            self.swap(source)
        except Exception as exc:  # PolicyRejected, or anything at all: refuse, keep running
            self.dropped_by["policy"] += 1
            self.refused(source, exc)

    def _fetch(self, cid: str) -> None:
        try:
            self.fetch(cid)
        except PolicyRejected as exc:
            self.dropped_by["policy"] += 1
            self.refused(cid, exc)
