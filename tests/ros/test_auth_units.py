"""The message authentication scheme alone (medc_common.auth; no ROS graph): key files, MACs,
tampering, another key, topic binding, freshness and replay."""

from __future__ import annotations

import os
import stat

import pytest
from medc_common import auth

TOPIC = "/medc/agent_0/move"
TYPE = "medc_interfaces/AgentMove"


class Clock:
    """A settable wall clock in ns."""

    def __init__(self, now_ns: int = 1_000_000_000_000) -> None:
        self.now_ns = now_ns

    def __call__(self) -> int:
        return self.now_ns


def signed(key: bytes, body: bytes = b"move 3", topic: str = TOPIC) -> bytes:
    return auth.compute_mac(key, topic, TYPE, body)


def test_key_file_is_private_and_read_back(tmp_path):
    path = auth.write_key_file(tmp_path / "mission.key")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    key = auth.load_key_file(path)
    assert len(key) == auth.KEY_BYTES
    assert auth.load_key_file(path) == key


def test_key_file_refusals(tmp_path):
    path = auth.write_key_file(tmp_path / "k")
    with pytest.raises(auth.AuthError, match="exists"):
        auth.write_key_file(path)
    os.chmod(path, 0o644)
    with pytest.raises(auth.AuthError, match="open to other users"):
        auth.load_key_file(path)
    bad = tmp_path / "short"
    bad.write_text("abcd\n")
    os.chmod(bad, 0o600)
    with pytest.raises(auth.AuthError, match="64 hex digits"):
        auth.load_key_file(bad)
    with pytest.raises(auth.AuthError, match="does not exist"):
        auth.load_key_file(tmp_path / "missing")
    link = tmp_path / "link"
    link.symlink_to(path)
    with pytest.raises(auth.AuthError, match="cannot open"):
        auth.load_key_file(link)
    with pytest.raises(auth.AuthError, match=r"cannot create|exists"):
        auth.write_key_file(link)
    with pytest.raises(auth.AuthError, match="not a regular file"):
        auth.load_key_file(tmp_path)


def test_key_file_setting_falls_back_to_environment(monkeypatch):
    monkeypatch.setenv(auth.KEY_FILE_ENV, "/run/k")
    assert auth.key_file_setting("") == "/run/k"
    assert auth.key_file_setting("/a") == "/a"
    monkeypatch.delenv(auth.KEY_FILE_ENV)
    assert auth.key_file_setting("") == ""


def test_genuine_message_verifies_once():
    key, clock = auth.new_key(), Clock()
    v = auth.Verifier(key, auth.ReplayGuard(clock_ns=clock))
    v.verify(TOPIC, TYPE, b"move 3", signed(key), "s1", 1, clock())
    with pytest.raises(auth.AuthError, match="replayed"):
        v.verify(TOPIC, TYPE, b"move 3", signed(key), "s1", 1, clock())
    v.verify(TOPIC, TYPE, b"move 3", signed(key), "s1", 2, clock())


@pytest.mark.parametrize("change", ["body", "topic", "key", "truncated", "unsigned"])
def test_forgeries_refused(change):
    key, clock = auth.new_key(), Clock()
    v = auth.Verifier(key, auth.ReplayGuard(clock_ns=clock))
    mac, body, topic, sender = signed(key), b"move 3", TOPIC, "s1"
    if change == "body":
        body = b"move 4"
    elif change == "topic":
        topic = "/medc/agent_1/move"
    elif change == "key":
        mac = signed(auth.new_key())
    elif change == "truncated":
        mac = mac[:16]
    else:
        mac, sender = b"", ""
    with pytest.raises(auth.AuthError):
        v.verify(topic, TYPE, body, mac, sender, 1, clock())


def test_fields_cannot_be_shifted_between_topic_type_and_body():
    key = auth.new_key()
    assert auth.compute_mac(key, "/a", "b", b"c") != auth.compute_mac(key, "/ab", "", b"c")
    assert auth.compute_mac(key, "/a", "b", b"c") != auth.compute_mac(key, "/a", "bc", b"")


def test_freshness_window():
    key, clock = auth.new_key(), Clock()
    v = auth.Verifier(key, auth.ReplayGuard(window_s=30, clock_ns=clock))
    for counter, offset_s, ok in [(1, -29, True), (2, 29, True), (3, -31, False), (4, 31, False)]:
        stamp = clock() + int(offset_s * 1e9)
        if ok:
            v.verify(TOPIC, TYPE, b"x", auth.compute_mac(key, TOPIC, TYPE, b"x"), "s", counter, stamp)
        else:
            with pytest.raises(auth.AuthError, match="stale or replayed"):
                v.verify(TOPIC, TYPE, b"x", auth.compute_mac(key, TOPIC, TYPE, b"x"), "s", counter, stamp)


def test_counters_are_per_sender_and_topic():
    clock = Clock()
    guard = auth.ReplayGuard(clock_ns=clock)
    guard.check("/t1", "a", 5, clock())
    guard.check("/t2", "a", 1, clock())  # another topic: its own counter
    guard.check("/t1", "b", 1, clock())  # another sender: its own counter
    with pytest.raises(auth.AuthError, match="not above 5"):
        guard.check("/t1", "a", 4, clock())


def test_forgotten_sender_is_bounded():
    clock = Clock()
    guard = auth.ReplayGuard(clock_ns=clock, max_senders=2)
    for sender in "abc":
        guard.check("/t", sender, 1, clock())
    assert len(guard._last) == 2


def test_signer_counts_per_topic():
    clock = Clock()
    s = auth.Signer(auth.new_key(), "s1", clock_ns=clock)
    assert s.next("/a") == (1, clock())
    assert s.next("/a")[0] == 2
    assert s.next("/b")[0] == 1


def test_bad_arguments():
    with pytest.raises(auth.AuthError):
        auth.Verifier(b"short")
    with pytest.raises(ValueError, match="sender"):
        auth.Signer(auth.new_key(), "")
    with pytest.raises(ValueError, match="window"):
        auth.ReplayGuard(window_s=0)


def test_verification_cost_is_small():
    """The per-message cost that a team pays (and a flood of forgeries costs a node)."""
    import time

    key, clock = auth.new_key(), Clock()
    v = auth.Verifier(key, auth.ReplayGuard(clock_ns=clock))
    body = bytes(120)
    mac = auth.compute_mac(key, TOPIC, TYPE, body)
    start = time.perf_counter()
    for i in range(1, 2001):
        v.verify(TOPIC, TYPE, body, mac, "s", i, clock())
    assert (time.perf_counter() - start) / 2000 < 1e-3


def test_canonical_encoding_is_what_the_receiver_rebuilds():
    """The bytes a MAC covers are the same after a trip through CDR (whose alignment padding is not),
    float32 fields included, and differ for any change of a field."""
    pytest.importorskip("medc_interfaces")
    from medc_common.auth_node import canonical
    from medc_interfaces.msg import EpisodeStatus
    from rclpy.serialization import deserialize_message, serialize_message

    msg = EpisodeStatus(session="s", agent_ids=["agent_0", "agent_1"], reward=0.1, step=3)
    back = deserialize_message(serialize_message(msg), EpisodeStatus)
    assert canonical(back) == canonical(msg)
    changed = deserialize_message(serialize_message(msg), EpisodeStatus)
    changed.agent_ids = ["agent_0", "agent_2"]
    assert canonical(changed) != canonical(msg)


def test_vouched_takes_only_the_matching_candidate():
    pytest.importorskip("medc_interfaces")
    from medc_common.auth_node import Vouched

    refused = []
    v = Vouched(refused.append, keys=2, per_key=2)
    assert v.offer("k", "forged", b"F") is None
    assert v.offer("k", "genuine", b"G") is None
    assert v.vouch("k", b"G") == "genuine"
    assert len(refused) == 1  # the forged candidate
    assert v.offer("k", "again", b"G") == "again"  # a re-send of the vouched one
    assert v.offer("k", "late forgery", b"X") is None and len(refused) == 2
    for i in range(5):  # a flood of unvouched keys is bounded and counted
        v.offer(f"flood{i}", "x", b"x")
    assert len(v._held) <= 2 and len(refused) >= 5


def test_heartbeats_are_signed_and_checked(tmp_path):
    """A signed DiagnosticArray verifies with the key once; an altered status, another key, an
    unsigned array or a replay does not."""
    pytest.importorskip("medc_interfaces")
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from medc_common.auth_node import NodeAuth
    from rclpy.serialization import deserialize_message, serialize_message

    key, other = auth.write_key_file(tmp_path / "k"), auth.write_key_file(tmp_path / "o")
    node, monitor = NodeAuth(str(key), "sim"), NodeAuth(str(key), "monitor")

    def beat(signer, message="running"):
        array = DiagnosticArray(status=[DiagnosticStatus(name="medc_sim", message=message)])
        signer.sign_diagnostics(array)
        return deserialize_message(serialize_message(array), DiagnosticArray)

    genuine = beat(node)
    replay = deserialize_message(serialize_message(genuine), DiagnosticArray)
    assert monitor.admit_diagnostics(genuine)
    assert [s.name for s in genuine.status] == ["medc_sim"]  # the auth status is taken off
    assert not monitor.admit_diagnostics(replay)
    altered = beat(node)
    altered.status[0].message = "all well"
    assert not monitor.admit_diagnostics(altered)
    assert not monitor.admit_diagnostics(beat(NodeAuth(str(other), "intruder")))
    assert not monitor.admit_diagnostics(DiagnosticArray(status=[DiagnosticStatus(name="medc_sim")]))
    assert monitor.refused["heartbeat"] == 4
    assert NodeAuth("", "open").admit_diagnostics(beat(node))  # the open mode takes anything
