"""The agent node's policy slot at run time: swaps by parameter, by topic (a path or a content id
fetched through the registry bridge), and refusals that keep the running policy.

A mixin of :class:`medc_agents.node.AgentNode`; the slot itself (validation, dry run, cache) is
:class:`medc_agents.policy.PolicySlot`.
"""

from __future__ import annotations

from medc_interfaces.srv import FetchBundle
from medc_training.untrusted import printable
from rcl_interfaces.msg import SetParametersResult
from std_msgs.msg import String

from medc_agents.policy import PolicyRejected, looks_like_cid, shown, strip_cid


def refusal_reason(exc: BaseException) -> str:
    """What a refusal says: the PolicyRejected text, or just the type of an unexpected error;
    printable ASCII only and bounded, as it goes to the log, /rosout and the caller."""
    text = str(exc) if isinstance(exc, PolicyRejected) else f"could not be loaded ({type(exc).__name__})"
    return printable(text, 2000)


class PolicySwaps:
    """Policy swaps of an agent node (its ``slot``, ``observer`` and ``swap_listeners``)."""

    def swap_policy(self, source: str) -> str:
        """Validate and run the bundle at ``source``; returns its description.

        Raises:
            PolicyRejected: refused; the previous policy keeps running.
        """
        loaded = self.slot.swap(source)
        self.observer.use_observation(self.slot.observation)
        self.get_logger().info(f"now running policy {loaded.description} "
                               f"(observation {self.observer.observation.name})")
        for listener in self.swap_listeners:
            listener(source, None)
        return loaded.description

    def _refused(self, source: str, exc: Exception) -> None:
        why = refusal_reason(exc)
        self.get_logger().error(f"policy {shown(source)} refused, keeping the running one: {why}")
        for listener in self.swap_listeners:
            try:
                listener(source, why)
            except Exception as err:  # a listener's bug must not turn a refusal into a crash
                self.get_logger().error(f"policy swap listener failed: {type(err).__name__}")

    def _on_set_parameters(self, params) -> SetParametersResult:
        for param in params:
            if param.name != "policy":
                continue
            try:
                self.swap_policy(str(param.value))
            except Exception as exc:  # PolicyRejected, or anything at all: refuse, keep running
                self._refused(str(param.value), exc)
                return SetParametersResult(successful=False, reason=refusal_reason(exc))
        return SetParametersResult(successful=True)

    def _on_policy_msg(self, msg: String) -> None:
        source = ""
        try:
            source = msg.data.strip()
            if looks_like_cid(source):
                self._request_fetch(strip_cid(source))
                return
            self.swap_policy(source)
        except Exception as exc:  # PolicyRejected, or anything at all: refuse, keep running
            self.dropped_by["policy"] += 1
            self._refused(source, exc)

    def _request_fetch(self, cid: str) -> None:
        if self._fetch_client is None:
            self._fetch_client = self.create_client(FetchBundle, self.bridge_service)
        if not self._fetch_client.service_is_ready():
            self.dropped_by["policy"] += 1
            self._refused(
                cid, PolicyRejected(f"registry bridge service {self.bridge_service} is not running")
            )
            return
        # The bridge verifies the bundle and publishes its local path on this agent's policy topic.
        self._fetch_client.call_async(FetchBundle.Request(cid=cid, agent_ids=[self.agent_id]))
        self.get_logger().info(f"asked the registry bridge for bundle {cid}")
