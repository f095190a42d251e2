"""The plain rules behind a team that survives a lost UAV and hostile messages (no node spinning):
medc_agents.guard, the simulator's MoveBook, the observer without a teammate, the grid's edge
tolerance (docs/ros-reference.md, "A lost UAV", "Moves are executed once", "Messages that contradict the
team's evidence", "Diagnostics")."""

from __future__ import annotations

import pytest
import torch
from builtin_interfaces.msg import Time
from medc_agents.guard import LostWatch, ReadingCheck, StatusGate
from medc_agents.team_state import TeamObserver
from medc_common.contract import GridGeometry
from medc_sim import messages
from medc_sim.moves import DuplicateAgent, MoveBook, MoveRejected
from medc_training.envs.tl_sensing import SENSING_PRESETS

IDS = ["agent_0", "agent_1", "agent_2"]


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _status(episode: int, step: int, session: str = "s1", map_sec: int = 1):
    return messages.status_msg(IDS, episode, step, Time(sec=10 + step), Time(sec=map_sec), session=session)


def test_a_move_is_executed_once_and_a_second_sender_is_a_duplicate():
    book = MoveBook(3, 8)
    book.open(0, 4)
    assert book.offer("agent_1", 0, 4, 2, "aaaa") == 1
    assert book.offer("agent_1", 0, 4, 2, "aaaa") is None  # a re-send: not executed again
    assert book.resent == 1
    with pytest.raises(DuplicateAgent, match="two processes claim agent_1"):
        book.offer("agent_1", 0, 4, 5, "bbbb")
    assert book.actions()[1] == 2  # the first move stands
    book.open(0, 5)
    assert book.offer("agent_1", 0, 4, 2, "aaaa") is None  # late re-send of the closed step
    with pytest.raises(DuplicateAgent):
        book.offer("agent_1", 0, 4, 2, "bbbb")
    with pytest.raises(MoveRejected, match="another graph"):
        book.offer("agent_1", 7, 0, 2, "cccc")  # an unknown sender for a step this driver never had


def test_two_moves_of_one_sender_with_different_actions_are_a_conflict_and_the_first_stands():
    from medc_sim.moves import ConflictingMove

    book = MoveBook(3, 8)
    book.open(0, 4)
    assert book.offer("agent_1", 0, 4, 2, "aaaa") == 1
    with pytest.raises(ConflictingMove, match=r"agent_1 \(sender aaaa\) sent two moves for episode 0 "
                       r"step 4 with different actions \(2, then 5\): the first \(2\) is executed, the "
                       r"second ignored"):
        book.offer("agent_1", 0, 4, 5, "aaaa")
    assert book.actions()[1] == 2 and book.conflicts == 1 and book.resent == 0
    assert book.offer("agent_1", 0, 4, 2, "aaaa") is None and book.resent == 1  # the same move: a re-send
    book.open(0, 5)
    with pytest.raises(ConflictingMove, match=r"the first \(2\) was executed"):
        book.offer("agent_1", 0, 4, 7, "aaaa")  # a late second answer to the step just flown
    assert book.conflicts == 2


def test_a_silent_agent_is_taken_out_and_comes_back_with_a_move():
    book = MoveBook(3, 8)
    book.open(0, 0)
    assert not book.complete
    book.take_out([0, 1, 2])
    assert not book.complete  # nobody answered: a stall, never stepped with every agent out
    book.lost.clear()
    book.offer("agent_0", 0, 0, 1, "a")
    book.offer("agent_1", 0, 0, 1, "b")
    book.take_out(book.missing)
    assert book.complete and book.actions() == [1, 1, None]
    book.open(0, 1)
    book.offer("agent_0", 0, 1, 1, "a")
    book.offer("agent_1", 0, 1, 1, "b")
    assert book.complete  # agent_2 is not waited for
    book.offer("agent_2", 0, 1, 3, "c")  # it moves again: back in the team
    assert book.lost == set() and book.returned == [2]



def test_only_a_move_received_after_the_take_out_brings_an_agent_back():
    """docs/ros-reference.md, "A lost UAV", rules 1-5: agent_2 answers step 3 and dies. Its answer to the
    previous step, received before it was taken out, does not bring it back; at step 4 the team
    steps without it. A previous-step move received after the take-out does (not executed; the
    step being collected then waits for its move)."""
    book = MoveBook(3, 8)
    book.open(0, 3)
    for k, sender in enumerate("abc"):
        book.offer(f"agent_{k}", 0, 3, 1, sender)  # agent_2's last answer
    assert book.complete
    book.open(0, 4)
    book.offer("agent_0", 0, 4, 1, "a")
    book.offer("agent_1", 0, 4, 1, "b")
    book.take_out(book.missing)  # move_timeout_s after the first move: agent_2 is out
    assert book.lost == {2} and book.complete  # its earlier answer does not count
    book.open(0, 5)
    book.offer("agent_0", 0, 5, 1, "a")
    book.offer("agent_1", 0, 5, 1, "b")
    assert book.complete and book.returned == []  # the team steps on without it
    book.open(0, 6)
    assert book.offer("agent_2", 0, 5, 1, "c") is None  # a late answer, received now: not executed
    assert book.lost == set() and book.returned == [2]
    book.offer("agent_0", 0, 6, 1, "a")
    book.offer("agent_1", 0, 6, 1, "b")
    assert not book.complete and book.missing == [2]  # back in the team: step 6 waits for it

def test_the_status_gate_holds_other_sessions_jumps_and_recovers():
    clock = Clock()
    gate = StatusGate(session_hold_s=1.0, recover_s=2.0, clock=clock)
    key = 1_000_000_000  # map_stamp Time(sec=1)
    assert gate.admit(_status(0, 0), -1, -1, -1, key)[0] == "take"
    assert gate.admit(_status(0, 1), 0, key, 0, key)[0] == "take"
    # Another driver while this one publishes: held and reported.
    verdict, why = gate.admit(_status(0, 0, "s2"), 0, key, 1, key)
    assert verdict == "hold" and "second driver or graph" in why and gate.foreign_now() == ["s2"]
    # Step 10^9 in the driver's own session: held until confirmed.
    verdict, why = gate.admit(_status(0, 10**9), 0, key, 1, key)
    assert verdict == "hold" and "jumps ahead" in why
    assert gate.admit(_status(0, 2), 0, key, 1, key)[0] == "take"  # the driver's next step goes on
    # A genuine jump is confirmed by the driver's next status (or by the same one recover_s later).
    assert gate.admit(_status(0, 5), 0, key, 2, key)[0] == "hold"
    assert gate.admit(_status(0, 6), 0, key, 2, key)[0] == "take"
    clock.t += 0.1
    assert gate.admit(_status(0, 9), 0, key, 6, key)[0] == "hold"
    clock.t += 2.5
    assert gate.admit(_status(0, 9), 0, key, 6, key)[0] == "take"
    # Statuses below the step answered for recover_s: the answered step was not the driver's.
    assert gate.admit(_status(0, 3), 0, key, 9, key)[0] == "drop"
    clock.t += 2.5
    verdict, why = gate.admit(_status(0, 4), 0, key, 9, key)
    assert verdict == "restart" and "following the driver" in why
    # The old session silent for session_hold_s: a new one is a restarted driver, followed.
    clock.t += 1.5
    assert gate.admit(_status(0, 0, "s3"), 0, key, 4, key)[0] == "take" and gate.session == "s3"


def test_a_teammate_is_lost_only_when_nothing_comes_from_it():
    clock = Clock()
    watch = LostWatch(3, own=0, timeout_s=1.5, clock=clock)
    for j in range(3):
        watch.seen("pose", j)
        watch.seen("reading", j)
    clock.t += 1.0
    assert watch.check({2: ["pose", "reading"]}, waiting_since=clock.t - 0.5) == []
    clock.t += 1.0
    assert watch.check({2: ["pose"]}, waiting_since=clock.t - 1.5, fresh={2}) == []  # mis-stamped, alive
    lost = watch.check({2: ["pose"], 0: ["reading"]}, waiting_since=clock.t - 1.5)
    assert [j for j, _ in lost] == [2] and "no pose for 1.5 s" in lost[0][1]  # never this agent itself
    assert watch.check({2: ["pose"]}, waiting_since=clock.t - 5) == []  # reported once
    assert watch.back(2) and not watch.back(2)


def test_the_observer_decides_without_an_absent_teammate():
    geo = GridGeometry(10, 10)
    o = TeamObserver("agent_0", 3, 10)
    o.add_map(messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0))
    for step in range(2):
        stamp = Time(sec=10 + step)
        for j in range(3 if step == 0 else 2):  # agent_2 silent from step 1 on
            o.add_pose(IDS[j], messages.pose_msg((j, step), stamp, geo))
            o.add_reading(IDS[j], messages.reading_msg(IDS[j], 5.0, 0.0, stamp))
        o.add_status(messages.status_msg(IDS, 0, step, stamp, Time(sec=1)))
        if step == 1:
            assert not o.ready() and o.missing() == {2: ["pose", "reading"]}
            o.absent.add(2)
        assert o.ready()
        _, mask, tick = o.observe()
        assert tick.step == step and mask.shape == (8,)
    assert o.positions[0, 2].tolist() == [2, 0]  # its last cell stays in the observation
    assert float(o.memory.visit_map.sum()) == 5  # 3 readings, then 2: none invented for agent_2


def test_a_pose_just_off_the_edge_snaps_and_one_far_off_names_the_distance():
    geo = GridGeometry(10, 10, 2.0)
    assert geo.xy_to_cell(-0.4, 5.0, tolerance=1.0) == (7, 0)
    assert geo.xy_to_cell(20.9, 19.5, tolerance=1.0) == (0, 9)
    with pytest.raises(ValueError, match=r"by 3\.000 m, more than the edge tolerance of 1 m"):
        geo.xy_to_cell(-3.0, 5.0, tolerance=1.0)
    o = TeamObserver("agent_0", 3, 10, edge_tolerance=0.5)
    o.add_map(messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0))
    o.add_status(_status(0, 0, map_sec=1))  # step 0, stamped 10 s, on the map
    pose = messages.pose_msg((0, 0), Time(sec=10), GridGeometry(10, 10))
    pose.pose.position.x = -5.0
    with pytest.raises(ValueError, match=r"pose of agent_1: .* by 5\.000 m"):
        o.add_pose("agent_1", pose)
    pose.pose.position.x = -0.3
    o.add_pose("agent_1", pose)  # within half a cell: the edge cell


def test_readings_in_the_wrong_units_are_warned_once():
    check = ReadingCheck(SENSING_PRESETS["paper-simple"], 3)
    warnings = [check.check(1, "agent_1", v / 1001) for v in [5.0, 12.0, 3.0, 40.0, 8.0, 2.0, 9.0, 6.0, 7.0]]
    said = [w for w in warnings if w]
    assert len(said) == 1 and "agent_1" in said[0] and "wrong units" in said[0]
    assert check.check(0, "agent_0", 1e6) and "above" in check.check(2, "agent_2", 5e4)
    assert check.check(0, "agent_0", 1e6) is None  # once per agent and kind
    fine = ReadingCheck(SENSING_PRESETS["realistic"], 1)
    assert all(fine.check(0, "agent_0", v) is None for v in [12, 30, 25, 400, 2100, 18, 33, 41, 27])
    # The fault is over once the last 8 readings of the agent are plausible: warned again if it comes back.
    assert all(check.check(1, "agent_1", v) is None for v in [5.0, 12.0, 3.0, 40.0, 8.0, 2.0, 9.0, 6.0])
    assert (1, "low") not in check.warned and (0, "high") in check.warned
    again = [w for w in (check.check(1, "agent_1", 1e-3) for _ in range(8)) if w]
    assert len(again) == 1 and "wrong units" in again[0]


def test_a_stall_says_whether_no_map_came_or_why_it_was_dropped():
    geo = GridGeometry(10, 10)
    o = TeamObserver("agent_0", 3, 10)
    stamp = Time(sec=10)
    for j in range(3):
        o.add_pose(IDS[j], messages.pose_msg((j, 0), stamp, geo))
        o.add_reading(IDS[j], messages.reading_msg(IDS[j], 5.0, 0.0, stamp))
    o.add_status(messages.status_msg(IDS, 0, 0, stamp, Time(sec=1)))
    need, have = o.waiting_for()
    assert any("the map with info.map_load_time 1.000000000" in n for n in need)
    assert "no map on the map topic" in have
    with pytest.raises(ValueError):
        o.add_map(messages.grid_msg(torch.zeros((8, 8), dtype=torch.bool), Time(sec=1), 1.0))
    need, have = o.waiting_for()
    assert have[0].startswith("that map was refused: map is 8x8"), have
