"""The poses and maps of a signing team, taken only once a verified message vouches for them.

A pose waits for the signed reading of its agent and step, a map for the signed status that names
its digest (:class:`medc_common.auth_node.Vouched`); a team that does not sign passes them through.
"""

from __future__ import annotations

from medc_common.auth_node import Vouched, message_digest

from medc_agents.team_messages import stamp_key


class SignedInputs:
    """Holds an agent's incoming poses and maps until vouched for, under its ``auth`` (the node's
    medc_common.auth_node checker: ``enabled``, ``refuse``)."""

    def __init__(self, auth) -> None:
        self.auth = auth
        self.poses = Vouched(lambda why: auth.refuse("pose", f"pose: {why}"))
        self.maps = Vouched(lambda why: auth.refuse("map", f"map: {why}"))

    def pose(self, agent_id: str, msg):
        """``msg``, agent ``agent_id``'s pose, when it can be taken now; else None (held)."""
        if not self.auth.enabled:
            return msg
        return self.poses.offer((agent_id, stamp_key(msg.header.stamp)), msg, message_digest(msg))

    def map(self, msg):
        """``msg``, a walls map, when it can be taken now; else None (held)."""
        if not self.auth.enabled:
            return msg
        return self.maps.offer(stamp_key(msg.info.map_load_time), msg, message_digest(msg))

    def pose_of(self, agent_id: str, reading):
        """The held pose of ``agent_id`` the verified ``reading`` vouches for, if any."""
        if not self.auth.enabled:
            return None
        return self.poses.vouch((agent_id, stamp_key(reading.header.stamp)), bytes(reading.pose_digest))

    def map_of(self, status):
        """The held map the verified episode ``status`` vouches for, if any."""
        if not self.auth.enabled:
            return None
        return self.maps.vouch(stamp_key(status.map_stamp), bytes(status.map_digest))
