"""The benchmark's oracle (medc_training.radbench.oracle): its lengths worked out by hand on small
scenarios, the same lengths played through the benchmark's world, and episode lines that pair with
the committed plays (none of which beats it)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from medc_training.radbench import BenchSet, Episode, load_sets, play_set
from medc_training.radbench.oracle import main, oracle_policy, oracle_results
from medc_training.radbench.pairing import load_episodes

ROOT = Path(__file__).resolve().parents[2]
SEARCHERS = ROOT / "docs/reproduction/radbench/searchers/g20-a3.episodes.jsonl"


pytestmark = pytest.mark.usefixtures("one_thread")


def _set(episodes: list[Episode], obstructions: int = 0) -> BenchSet:
    return BenchSet("hand", 20, 1.0, len(episodes[0].starts), 120, obstructions, "none", tuple(episodes),
                    "0" * 64)


def _episode(source, starts, obstructions=()) -> Episode:
    return Episode(source, 500.0, 20, tuple(starts), tuple(obstructions), 7)


def _lengths(bench_set: BenchSet) -> list[tuple[int, bool]]:
    return [(r.length, r.success) for r in oracle_results(bench_set)]


def _played(bench_set: BenchSet) -> list[tuple[int, bool]]:
    return [(r.length, r.success) for r in play_set(bench_set, oracle_policy)]


def test_open_grid_chebyshev_distance_less_the_side_neighbours():
    # The source's cell and its 4 side neighbours (d <= 1.1 m) end the episode, its diagonal
    # neighbours (1.41 m) do not: Chebyshev distance - 1, except on the source's diagonals.
    src = (10, 10)
    cases = {(0, 10): 9, (10, 0): 9, (0, 0): 10, (19, 19): 9, (0, 3): 9, (2, 5): 7, (4, 16): 6,
             (12, 10): 1, (11, 11): 1}
    s = _set([_episode(src, [start]) for start in cases])
    assert _lengths(s) == [(d, True) for d in cases.values()]
    assert _played(s) == _lengths(s)


def test_the_team_length_is_the_nearest_agent():
    # Alone: (0,0) 10, (2,5) 7, (19,19) 9, (0,19) and (19,0) 9 (10 rows and 9 columns away).
    s = _set([_episode((10, 10), [(0, 0), (2, 5), (19, 19)]), _episode((10, 10), [(0, 0), (0, 19), (19, 0)])])
    assert _lengths(s) == [(7, True), (9, True)]
    assert _played(s) == _lengths(s)


def test_an_obstruction_forces_a_detour():
    # A wall in columns 6-7, rows 5-15, between the agent and the source: 7 moves in the open,
    # around it 12: (9,3) (8,4) (7,5) (6,5) (5,5) (4,6) past the corner, (4,7), then 5 down to (9,10).
    open_ = _episode((10, 10), [(10, 2)])
    walled = _episode((10, 10), [(10, 2)], [(5, 6, 15, 7)])
    assert _lengths(_set([open_])) == [(7, True)]
    s = _set([walled], 1)
    assert _lengths(s) == [(12, True)]
    assert _played(s) == [(12, True)]


def test_a_diagonal_move_between_two_obstruction_corners_is_allowed():
    # Rows 0-9 x columns 0-4 are closed by a wall in column 5 (rows 0-9) and one in row 10
    # (columns 0-4), the grid's edges, and the corner gap (9,4) -> (10,5): 5 moves to it, then
    # 5 to (14,0) or (15,1).
    s = _set([_episode((15, 0), [(5, 2)], [(0, 5, 9, 5), (10, 0, 10, 4)])], 2)
    assert _lengths(s) == [(10, True)]
    assert _played(s) == [(10, True)]


def test_a_start_on_a_success_cell_still_takes_one_move():
    # The world checks for the source after each move, never at the starts.
    s = _set([_episode((10, 10), [(10, 10)]), _episode((0, 0), [(0, 1)]), _episode((10, 10), [(9, 10)])])
    assert _lengths(s) == [(1, True)] * 3
    assert _played(s) == [(1, True)] * 3


def test_a_source_no_agent_can_reach_fails_at_the_step_limit():
    s = _set([_episode((0, 0), [(10, 10)], [(0, 2, 2, 2), (2, 0, 2, 1)])], 2)
    assert _lengths(s) == [(120, False)]
    assert _played(s) == [(120, False)]


def test_frozen_episodes_end_found_in_the_world_at_the_oracle_length():
    for s in load_sets(20, 3, obstructions=[0, 7], snrs=["low", "high"]):
        head = s.head(6)
        want = _lengths(head)
        assert all(ok for _, ok in want)
        assert _played(head) == want


def test_episode_lines_pair_with_the_committed_plays_and_none_beats_the_oracle(tmp_path, capsys):
    out = tmp_path / "oracle.episodes.jsonl"
    assert main(["--episodes", "40", "--out", str(out)]) == 0
    assert "obs5-7" in capsys.readouterr().out
    first = json.loads(out.read_text().splitlines()[0])
    assert first["policy"] == "oracle" and first["run"] == 0 and first["success"] is True
    assert first["declared_step"] is None and first["track_rmse_m"] is None
    episodes = load_episodes([SEARCHERS, out])
    oracle = episodes.pop("oracle")
    assert len(oracle) == 24 * 40
    for policy, played in episodes.items():
        assert set(played) == set(oracle), policy
        assert all(r.length >= oracle[k].length for k, r in played.items() if r.success), policy
