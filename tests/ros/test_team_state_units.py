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
