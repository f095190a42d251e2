"""The units an agent's TeamObserver is made of, each on its own (no node, no observer): the
episode clock, the map store, the rounds of poses and readings, the map check, the team memory."""

from __future__ import annotations

import pytest
import torch
from builtin_interfaces.msg import Time
from medc_agents.team_episode import EpisodeClock, Tick
from medc_agents.team_inputs import KEEP_MAPS, STAMP_HISTORY, MapStore, TeamRounds
from medc_agents.team_memory import AgentMemory
from medc_agents.team_messages import map_from_message, stamp_key
from medc_common.contract import GridGeometry
from medc_sim import messages
from medc_training.envs.tl_observation import parse_observation
from medc_training.envs.tl_sensing import parse_sensing

IDS = ["agent_0", "agent_1", "agent_2"]
GEO = GridGeometry(10, 10, 1.0)
S = 1_000_000_000  # one second as a stamp key


def _status(episode: int, step: int, sec: int, map_sec: int, done: bool = False, ids=IDS):
    msg = messages.status_msg(ids, episode, step, Time(sec=sec), Time(sec=map_sec))
    msg.done = done
    return msg


# ---------------------------------------------------------------- the episode clock
def test_clock_answers_each_step_once_and_refuses_older_steps():
    clock = EpisodeClock()
    tick = clock.take_status(_status(2, 0, 10, 1), IDS)
    assert tick == Tick(2, 0, 10 * S, 1 * S) and clock.open_tick() == tick
    assert clock.advance(tick) == (True, None)  # the first step starts the memory
    assert clock.open_tick() is None and clock.answered(tick)
    assert clock.take_status(_status(2, 0, 10, 1), IDS) == tick  # a re-send: answered already
    assert clock.open_tick() is None
    nxt = clock.take_status(_status(2, 1, 11, 1), IDS)
    assert clock.advance(nxt) == (False, None)  # the same episode goes on
    clock.advance(clock.take_status(_status(2, 2, 12, 1), IDS))
    with pytest.raises(ValueError, match="older than the one answered"):
        clock.take_status(_status(2, 1, 13, 1), IDS)
    with pytest.raises(ValueError, match="this team is"):
        clock.take_status(_status(2, 3, 13, 1, ids=IDS[:2]), [*IDS[:2], "agent_9"])
    assert clock.take_status(_status(2, 3, 13, 1, done=True), IDS) is None
    assert clock.maps_in_use() == (1 * S, 1 * S)


def test_clock_starts_afresh_on_a_new_episode_a_new_map_step_zero_or_a_restart():
    clock = EpisodeClock()
    clock.advance(Tick(0, 0, 1, 7))
    clock.advance(Tick(0, 1, 2, 7))
    assert clock.advance(Tick(1, 0, 3, 7))[0]  # next episode
    assert clock.advance(Tick(1, 1, 4, 8))[0]  # another map
    fresh, note = clock.advance(Tick(0, 0, 5, 9))  # the driver went back: said once
    assert fresh and "the driver restarted" in note
    clock.advance(Tick(0, 1, 6, 9))
    clock.restart()  # told to follow the driver again: no note
    assert clock.step == -1
    assert clock.advance(Tick(0, 1, 7, 9)) == (True, None)
    assert clock.advance(Tick(0, 2, 8, 9)) == (False, None)


# ---------------------------------------------------------------- maps
def test_map_store_keeps_the_last_maps_but_never_the_teams():
    store = MapStore()
    walls = torch.zeros((10, 10), dtype=torch.bool)
    store.put(1, walls, GEO, 1, keep=(None, 1))
    for load in range(2, 2 + KEEP_MAPS + 3):  # a burst of other maps
        store.put(load, walls, GEO, load, keep=(None, 1))
    assert 1 in store and len(store) == KEEP_MAPS  # the team's map and the latest others
    assert store.geometry(1) is GEO and store.entry(2) is None and KEEP_MAPS + 4 in store
    assert store.latest is GEO


def test_map_store_says_what_a_step_lacks():
    store = MapStore()
    need, have = store.explain_missing(7 * S)
    assert need == ["the map with info.map_load_time 7.000000000 (the status's map_stamp)"]
    assert have == ["no map on the map topic"]
    store.last_drop = "map with map_load_time 7.000000000: map is 9x9"
    assert store.explain_missing(7 * S)[1] == [f"no usable map: the last one was dropped ({store.last_drop})"]
    store.put(0, torch.zeros((10, 10), dtype=torch.bool), GEO, 7 * S, keep=())  # stamped apart
    have = store.explain_missing(7 * S)[1]
    assert have[0] == "maps with info.map_load_time 0.000000000"
    assert "header.stamp is 7.000000000 has info.map_load_time 0.000000000" in have[1]
    assert store.explain_missing(0) == ([], [])


def test_map_check_takes_the_grid_size_the_observation_allows():
    walls = torch.zeros((13, 13), dtype=torch.bool)
    msg = messages.grid_msg(walls, Time(sec=1), 2.0)
    with pytest.raises(ValueError, match="shows the whole 10x10 grid"):
        map_from_message(msg, 10, False, "maps", False)
    got, geometry = map_from_message(msg, 10, True, "ego6", False)  # an agent-centred window: any size
    assert got.shape == (13, 13) and geometry.resolution == 2.0
    with pytest.raises(ValueError, match="resolution is 2 m"):
        map_from_message(msg, 13, False, "maps", False, resolution=1.0)
    ell = walls.clone()
    ell[4, 2:6] = True
    ell[5:8, 2] = True  # an L: the exact line of sight cannot take it as one rectangle
    ell_msg = messages.grid_msg(ell, Time(sec=1), 1.0)
    assert map_from_message(ell_msg, 13, False, "maps", exact=False)[0].sum() == 7
    with pytest.raises(ValueError, match="straight segments"):
        map_from_message(ell_msg, 13, False, "maps", exact=True)


# ---------------------------------------------------------------- poses and readings
def _full_round(rounds: TeamRounds, key: int, cells) -> None:
    for j, cell in enumerate(cells):
        msg = messages.pose_msg(cell, Time(sec=key // S, nanosec=key % S), GEO)
        rounds.add("pose", j, key, (msg.pose.position.x, msg.pose.position.y))
        rounds.add("reading", j, key, 5.0 + j)


def test_rounds_say_who_is_missing_and_let_an_absent_teammate_keep_its_cell():
    rounds = TeamRounds(3)
    _full_round(rounds, 1 * S, [(1, 1), (2, 2), (3, 3)])
    assert rounds.present(1 * S) == [0, 1, 2] and rounds.readings_complete(1 * S)
    assert rounds.cells(1 * S, GEO, 0.5, own=0) == [(1, 1), (2, 2), (3, 3)]
    rounds.remember_cells([(1, 1), (2, 2), (3, 3)], [0, 1, 2])
    rounds.release(1 * S)
    assert rounds.present(1 * S) == []
    # agent_2 goes silent: the round waits for it until it is taken out of the team.
    xy = (4.5, 5.5)
    rounds.add("pose", 0, 2 * S, xy)
    rounds.add("reading", 0, 2 * S, 1.0)
    rounds.add("pose", 1, 2 * S, xy)
    rounds.add("reading", 1, 2 * S, 1.0)
    assert rounds.missing(2 * S) == {2: ["pose", "reading"]}
    assert not rounds.readings_complete(2 * S) and rounds.cells(2 * S, GEO, 0.5, own=0) is None
    need, have = rounds.explain(2 * S, IDS)
    assert need == ["the pose of agent_2 stamped 2.000000000", "the reading of agent_2 stamped 2.000000000"]
    assert have[0] == "latest pose of agent_2 stamped 1.000000000 (-1000000.000 us from the status)"
    rounds.absent.add(2)
    assert rounds.readings_complete(2 * S) and rounds.explain(2 * S, IDS) == ([], [])
    cells = rounds.cells(2 * S, GEO, 0.5, own=0)
    assert cells[:2] == [(4, 4), (4, 4)] and cells[2] == (3, 3)  # its last cell stays
    assert rounds.latest_xy()[0] == xy


def test_rounds_find_an_orphan_round_and_keep_a_bounded_history():
    rounds = TeamRounds(3)
    _full_round(rounds, 5 * S, [(1, 1), (2, 2), (3, 3)])
    assert rounds.orphan(answered=-1, pending=None) == 5 * S
    assert rounds.orphan(answered=-1, pending=5 * S) is None  # the pending step's own round
    assert rounds.orphan(answered=5 * S, pending=None) is None  # answered already
    for k in range(STAMP_HISTORY + 4):
        rounds.add("pose", 0, (10 + k) * S, (0.5, 0.5))
    assert rounds.missing(10 * S) == {j: ["pose", "reading"] for j in range(3)}  # let go of
    assert rounds.missing((9 + STAMP_HISTORY + 4) * S)[0] == ["reading"]
    rounds.drop("reading", 1, "reading -1.0 is not a finite non-negative number")
    assert any("last reading of agent_1 dropped" in h for h in rounds.explain(30 * S, IDS)[1])
    off = TeamRounds(3)
    off.add("pose", 1, 1 * S, (40.0, 1.0))
    need, have = off.explain_off_grid(1 * S, GEO, 0.5, IDS)
    assert need == ["a pose of agent_1 on the map"] and have[0].startswith("agent_1: ")


# ---------------------------------------------------------------- the team memory
def test_agent_memory_follows_the_maps_grid_and_builds_the_observation():
    memory = AgentMemory(10, parse_sensing("paper-simple"))
    walls = torch.zeros((1, 13, 13), dtype=torch.bool)
    positions = torch.tensor([[[1, 1], [6, 6], [12, 12]]])
    readings = torch.tensor([[1.0, 2.0, 3.0]])
    memory.record(walls, positions, readings, fresh=True)
    assert memory.grid == 13 and float(memory.memory.visit_map.sum()) == 3
    memory.record(walls, positions[:, :2], readings[:, :2], fresh=False)  # one teammate out
    assert float(memory.memory.visit_map.sum()) == 5
    obs, mask = memory.observe(parse_observation("ego3+estimate"), positions, walls, index=2)
    assert obs.shape[-2:] == (7, 7) and mask.shape == (8,)
    assert not bool(mask[2])  # E of the corner cell (12, 12) leaves the grid
    assert torch.equal(memory.positions, positions) and memory.team_mask.shape == (1, 3, 8)


def test_stamp_keys_are_integer_nanoseconds():
    assert stamp_key(Time(sec=3, nanosec=7)) == 3 * S + 7


# ---------------------------------------------------------------- faults the stall report and the checks name
def test_a_refused_maps_stall_report_says_why_it_was_refused():
    from medc_agents.team_state import TeamObserver

    o = TeamObserver("agent_0", 3, 10)
    walls = torch.zeros((10, 10), dtype=torch.bool)
    for sec in (1, 2, 3):  # older maps held
        o.add_map(messages.grid_msg(walls, Time(sec=sec), 1.0))
    with pytest.raises(ValueError, match="8x8"):
        o.add_map(messages.grid_msg(torch.zeros((8, 8), dtype=torch.bool), Time(sec=9), 1.0))
    o.add_status(_status(1, 0, 20, 9))  # the step names the refused map
    need, have = o.waiting_for()
    assert need[0] == "the map with info.map_load_time 9.000000000 (the status's map_stamp)"
    assert have[0] == ("that map was refused: map is 8x8, but this agent's observation 'maps' shows the "
                       "whole 10x10 grid its policy was trained on: publish a map of that size, or run a "
                       "policy with an agent-centred observation (egoR), which plays any size"), have
    assert not any("maps with info.map_load_time" in h for h in have)  # not a list of older maps
    o.add_map(messages.grid_msg(walls, Time(sec=9), 1.0))  # sent again, right: the step has its map
    assert not any("map" in n for n in o.waiting_for()[0])


def _play_step(o, episode: int, step: int, sec: int, map_sec: int, geo, cells, map_msg=None,
               map_first: bool = True):
    """Feed one team step to observer ``o`` as a driver does (map first at step 0 unless
    ``map_first`` is False, poses and readings, then the status); returns the drops it raised."""
    raised = []
    if map_msg is not None and map_first:
        o.add_map(map_msg)
    for j, cell in enumerate(cells):
        try:
            o.add_pose(IDS[j], messages.pose_msg(cell, Time(sec=sec), geo))
        except ValueError as exc:
            raised.append(str(exc))
        o.add_reading(IDS[j], messages.reading_msg(IDS[j], 2.0, 0.0, Time(sec=sec)))
    if map_msg is not None and not map_first:
        o.add_map(map_msg)
    o.add_status(_status(episode, step, sec, map_sec))
    return raised


@pytest.mark.parametrize("map_first", [True, False])
def test_the_first_poses_on_a_new_area_are_checked_against_its_map(map_first):
    from medc_agents.team_state import TeamObserver

    o = TeamObserver("agent_0", 3, 10, observation="ego6")
    here = messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0)
    assert _play_step(o, 0, 0, 10, 1, GEO, [(1, 1), (2, 2), (3, 3)], here) == []
    assert o.ready() and o.observe()[2].step == 0
    # The next episode flies a new area: 12x12 cells of 2 m, 500 m away. Its map comes with (or,
    # map_first False, just after) the first poses on it: none is dropped, the step is decided.
    far = GridGeometry(12, 12, 2.0, 500.0, 500.0)
    new_map = messages.grid_msg(torch.zeros((12, 12), dtype=torch.bool), Time(sec=30), 2.0)
    new_map.info.origin.position.x = new_map.info.origin.position.y = 500.0
    raised = _play_step(o, 1, 0, 31, 30, far, [(0, 0), (5, 5), (11, 11)], new_map, map_first)
    assert raised == [] and o.late_drops == []
    assert o.ready() and o.late_drops == []
    _, _, tick = o.observe()
    assert (tick.episode, tick.step) == (1, 0) and o.positions[0].tolist() == [[0, 0], [5, 5], [11, 11]]
    # A pose off the map of its step is still dropped, with the reason: at once when its status
    # came first, else once the status names the map.
    pose = messages.pose_msg((0, 0), Time(sec=32), GEO)  # on the old area
    o.add_pose("agent_1", pose)  # its step is not known yet: held unchecked
    o.add_status(_status(1, 1, 32, 30))
    assert not o.ready() and len(o.late_drops) == 1 and "pose of agent_1" in o.late_drops[0]
    assert "outside" in o.late_drops[0] or "off" in o.late_drops[0]
    with pytest.raises(ValueError, match="pose of agent_2"):
        o.add_pose("agent_2", pose)  # its status is here: checked against its map at once
    assert "pose" in o.missing()[1]  # the dropped pose is missing, not used


class _Health:
    """The conditions a MapFaults sets, as a node's Health keeps them."""

    def __init__(self) -> None:
        self.states: dict[str, tuple[bytes, str]] = {}

    def set(self, part: str, level: bytes, message: str, values=None, log: bool = True) -> None:
        self.states[part] = (level, message)

    def level(self, part: str) -> bytes:
        from diagnostic_msgs.msg import DiagnosticStatus

        return self.states.get(part, (DiagnosticStatus.OK, ""))[0]


def test_a_map_fault_is_over_once_a_later_status_is_decided_on_the_drivers_map_even_an_older_one():
    """A driver that sends one map for the whole mission: a map from elsewhere, then one refused,
    each WARN until a step whose status came after it is decided on the driver's map (which came
    before them); the step waiting when the fault came does not end it."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from medc_agents.map_faults import MapFaults
    from medc_agents.team_state import TeamObserver

    o = TeamObserver("agent_0", 3, 10)
    health = _Health()
    faults = MapFaults(o, health, logger=None)
    cells = [(1, 1), (2, 2), (3, 3)]
    mission = messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0)
    o.add_map(mission)
    faults.taken(1 * S)
    _play_step(o, 0, 0, 10, 1, GEO, cells)
    faults.decided(o.observe()[2])
    assert faults.checks == {}  # the status names it: no check

    elsewhere = messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=5), 1.0)
    elsewhere.info.origin.position.x = elsewhere.info.origin.position.y = 500.0
    _play_step(o, 0, 1, 11, 1, GEO, cells)  # step 1 waits while the map from elsewhere comes
    o.add_map(elsewhere)
    faults.taken(5 * S)
    faults.check(5 * S)
    level, message = health.states["map"]
    assert level == DiagnosticStatus.WARN and "holds none of the team's 3 latest poses" in message
    faults.decided(o.observe()[2])  # the step that was waiting: not past the fault
    assert health.level("map") == DiagnosticStatus.WARN
    _play_step(o, 0, 2, 12, 1, GEO, cells)  # a status after the fault, on the mission's map
    faults.decided(o.observe()[2])
    assert health.states["map"] == (DiagnosticStatus.OK, "deciding on the map with map_load_time "
                                    "1.000000000, which the episode status names")
    assert faults.fault is None

    with pytest.raises(ValueError, match="8x8") as refused:
        o.add_map(messages.grid_msg(torch.zeros((8, 8), dtype=torch.bool), Time(sec=9), 1.0))
    faults.refused(9 * S, refused.value)
    assert health.states["map"][1].startswith("map with map_load_time 9.000000000 refused: map is 8x8")
    _play_step(o, 0, 3, 13, 1, GEO, cells)  # the driver goes on with its own map
    faults.decided(o.observe()[2])
    assert health.level("map") == DiagnosticStatus.OK and faults.fault is None
