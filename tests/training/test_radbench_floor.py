"""The floor of a benchmark episode (medc_training.radbench.floor), on hand-drawn layouts."""

from __future__ import annotations

import json

import pytest
from medc_training.radbench.floor import episode_floor, main
from medc_training.radbench.scenario import Episode


def _episode(source, starts, obstructions=()):
    return Episode(source=source, strength=500.0, background=20, starts=tuple(starts),
                   obstructions=tuple(obstructions), noise_seed=1)


def test_open_area_diagonal_moves_and_the_success_radius():
    # 12 cells east of the source: 11 moves reach the cell next to it (within 1.1 m)
    assert episode_floor(_episode((5, 5), [(5, 17)]), 20) == 11
    # diagonal moves count one each; (9, 9) is 1.41 m from (10, 10), outside the radius, so the
    # nearest goal cells are (9, 10) and (10, 9): 10 moves from (0, 0)
    assert episode_floor(_episode((10, 10), [(0, 0)]), 20) == 10
    # the nearest agent decides
    assert episode_floor(_episode((5, 5), [(5, 17), (15, 5), (5, 9)]), 20) == 3


def test_walls_make_the_agent_walk_around():
    # a wall from row 0 to row 8 in column 10 between a start at (0, 5) and a source at (0, 15)
    wall = (0, 10, 8, 10)
    open_floor = episode_floor(_episode((0, 15), [(0, 5)]), 20)
    walled = episode_floor(_episode((0, 15), [(0, 5)], [wall]), 20)
    assert open_floor == 9
    # down to row 9 to pass under the wall's end, then back up: 9 moves down and 9 up at least
    assert walled == 17


def test_an_unreachable_source_is_refused():
    ring = [(8, 8, 8, 12), (12, 8, 12, 12), (9, 8, 11, 8), (9, 12, 11, 12)]  # seals cells 9..11 x 9..11
    with pytest.raises(ValueError, match="no agent"):
        episode_floor(_episode((2, 2), [(10, 10)], ring), 20)
    assert episode_floor(_episode((2, 2), [(10, 10), (2, 6)], ring), 20) == 3  # the other agent can


def test_command_line_on_the_frozen_file(capsys):
    assert main(["--grid", "20", "--agents", "3", "--episodes", "4", "--sets-file", "/nonexistent"]) == 2
    assert main(["--grid", "20", "--agents", "3", "--episodes", "4"]) == 0
    table = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert table["episodes"] == 24 * 4 and set(table["per_count"]) == {str(c) for c in range(8)}
    assert 8.0 < table["all"] < 12.0  # sources are at least 10 m from every start
