"""The benchmark's scenario generator, frozen sets and metrics (medc_training.radbench): RAD-A2C's
SNR bins and start-distance rule on hand cases, every frozen episode obeying the rules, the sets
loading only with their SHA-256 (a changed file is refused), and the field's figures on hand-computed
cases."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from medc_training.radbench import sets
from medc_training.radbench.results import EpisodeResult, median_ci, paired, sign_test, summarize, wilson
from medc_training.radbench.scenario import (
    GRIDS,
    MIN_START_M,
    OBSTRUCTION_SIDE,
    SNR_BINS,
    Episode,
    generate_set,
    line_of_sight_blocked,
    noise_uniforms,
    snr,
    snr_bin,
    start_distance_ok,
    subbin_edges,
)
from medc_training.radbench.sets import FROZEN, SETS_DIR, SetFileError, load_file, load_sets, set_digest
from medc_training.stats import t95

# ------------------------------------------------------------------ SNR and start distance


def test_snr_is_signal_plus_background_over_background_in_radas_units():
    # S counts/s at 1 m, B counts/s, d² in m²: RAD-A2C's I = 1e7 counts/s at 1 cm is S = 1000.
    assert snr(1000.0, 10, 100.0) == pytest.approx(2.0)
    assert snr(400.0, 20, 100.0) == pytest.approx(1.2)
    assert snr(100.0, 50, 400.0) == pytest.approx(1.005)
    assert snr(1e7 / 1e4, 10, (1000 / 100) ** 2) == pytest.approx((1e7 / 1000**2 + 10) / 10)


def test_snr_bins_are_open_below_and_closed_above():
    assert snr_bin(1.0) is None and snr_bin(1.0001) == "low"
    assert snr_bin(1.2) == "low" and snr_bin(1.2000001) == "medium"
    assert snr_bin(1.6) == "medium" and snr_bin(1.61) == "high"
    assert snr_bin(2.0) == "high" and snr_bin(2.0001) is None
    assert snr_bin(snr(1000.0, 10, 100.0)) == "high"  # strongest source at 10 m, lowest background
    assert subbin_edges("low") == (1.0, 1.05, 1.1, 1.15, 1.2)
    assert subbin_edges("medium") == (1.2, 1.3, 1.4, 1.5, 1.6)
    assert subbin_edges("high") == (1.6, 1.7, 1.8, 1.9, 2.0)
    with pytest.raises(ValueError, match="choose one of low, medium, high"):
        subbin_edges("loud")


def test_every_start_is_at_least_10_m_from_the_source():
    assert MIN_START_M == 10.0
    assert start_distance_ok([(6, 8)], (0, 0))  # exactly 10 m
    assert start_distance_ok([(10, 0)], (0, 0))
    assert not start_distance_ok([(6, 7)], (0, 0))  # sqrt(85) m
    assert not start_distance_ok([(9, 4)], (0, 0))  # sqrt(97) m
    assert not start_distance_ok([(19, 19), (0, 9), (19, 0)], (0, 0))  # one of three too near
    assert start_distance_ok([(19, 19), (0, 10), (19, 0)], (0, 0))
    assert not start_distance_ok([(5, 4)], (0, 0), cell_m=1.5)  # 9.6 m with 1.5 m cells


def _check_rules(e: Episode, grid: int, obstructions: int, name: str, subbin: int | None) -> None:
    """Every rule of the generator on one episode (scenario module docstring)."""
    walls = e.walls(grid)
    lo, hi = OBSTRUCTION_SIDE
    assert len(e.obstructions) == obstructions
    for i, (r0, c0, r1, c1) in enumerate(e.obstructions):
        assert r0 < GRIDS[grid].corner_cells and c0 < GRIDS[grid].corner_cells
        for first, last in ((r0, r1), (c0, c1)):  # 2-5 cells, shorter only where the grid's edge clips it
            assert last - first + 1 <= hi and (last - first + 1 >= lo or last == grid - 1)
        for other in e.obstructions[i + 1:]:
            gap = max(other[0] - r1, r0 - other[2], other[1] - c1, c0 - other[3])
            assert gap >= 2, "two obstructions touch"
    assert not walls[e.source] and not any(walls[s] for s in e.starts)
    assert len(set(e.starts)) == len(e.starts)
    assert start_distance_ok(e.starts, e.source, GRIDS[grid].cell_m)
    assert 100.0 <= e.strength < 1000.0 and abs(e.strength * 100 - round(e.strength * 100)) < 1e-6
    assert 10 <= e.background <= 50
    values = e.snrs(GRIDS[grid].cell_m)
    if name != "none":
        team = max(values)
        assert snr_bin(team) == name
        edges = subbin_edges(name)
        assert edges[subbin] < team <= edges[subbin + 1]


@pytest.mark.parametrize(("agents", "obstructions", "name"), [(1, 0, "high"), (1, 5, "low"), (3, 7, "medium"),
                                                              (3, 2, "high")])
def test_generated_episodes_obey_every_rule_and_the_seed_decides_them(agents, obstructions, name):
    episodes, stats = generate_set(20, agents, obstructions, name, episodes=12)
    assert len(episodes) == 12 and stats.accepted == 12 and stats.geometries >= 12
    for i, e in enumerate(episodes):
        assert len(e.starts) == agents
        _check_rules(e, 20, obstructions, name, i % 4)  # interleaved sub-bins
    again, _ = generate_set(20, agents, obstructions, name, episodes=12)
    other, _ = generate_set(20, agents, obstructions, name, episodes=12, seed=7)
    assert again == episodes and other != episodes


def test_the_source_hides_from_every_start_when_21_candidates_allow():
    episodes, stats = generate_set(20, 1, 4, "none", episodes=40)
    hidden = [bool(line_of_sight_blocked(e.starts[0], e.source, e.obstructions)) for e in episodes]
    assert sum(hidden) == len(episodes) - stats.source_in_sight
    assert sum(hidden) >= 0.8 * len(episodes)


def test_generator_refuses_bad_arguments():
    for kwargs, match in (({"grid": 25}, "grid must be one of"), ({"agents": 0}, "agents must be"),
                          ({"obstructions": 8}, "obstructions must be"), ({"snr_name": "x"}, "unknown SNR")):
        args = {"grid": 20, "agents": 1, "obstructions": 0, "snr_name": "low", **kwargs}
        with pytest.raises(ValueError, match=match):
            generate_set(**args, episodes=4)


def test_line_of_sight_is_the_environments_exact_rule():
    import torch
    from medc_training.envs.tl_sensing import geometric_factor, wall_rectangles
    from medc_training.radbench.play import TEAM_SENSING

    episodes, _ = generate_set(20, 3, 7, "none", episodes=6)
    g = 20
    idx = np.arange(g * g)
    cells = np.stack((idx // g, idx % g), 1)
    for e in episodes:
        walls = torch.from_numpy(e.walls(g)).unsqueeze(0)
        starts = torch.tensor([e.starts])
        rects = wall_rectangles(walls, 7)
        clear = geometric_factor(TEAM_SENSING, starts, torch.from_numpy(cells), walls, rects)[0] > 0  # [N,G²]
        ours = line_of_sight_blocked(np.array(e.starts)[:, None, :], cells[None], e.obstructions)
        free = ~e.walls(g).ravel()
        assert np.array_equal(ours[:, free], ~clear.numpy()[:, free])
    assert not line_of_sight_blocked((0, 0), (0, 5), [])
    assert line_of_sight_blocked((0, 0), (0, 5), [(0, 2, 0, 2)])
    assert not line_of_sight_blocked((0, 0), (2, 2), [(0, 2, 0, 3)])  # grazes the corner only


def test_the_generators_source_check_answers_as_the_line_of_sight_rule():
    from medc_training.radbench.scenario import _hidden_from_all

    rng = np.random.default_rng(7)
    g = 20
    idx = np.arange(g * g)
    cells = np.stack((idx // g, idx % g), 1)
    episodes, _ = generate_set(20, 3, 7, "none", episodes=8)
    checked = 0
    for e in episodes:
        starts = np.array(e.starts)
        rects = list(e.obstructions)
        # every cell as the source, and starts in the same row or column as it (flat segments)
        for source in cells[rng.permutation(len(cells))[:120]]:
            for these in (starts, np.array([[source[0], 0], [0, source[1]], starts[0]])):
                expected = bool(line_of_sight_blocked(these, source, rects).all())
                assert _hidden_from_all(these, source, rects) == expected
                checked += 1
    assert checked == 8 * 120 * 2
    # a segment that only grazes a corner is clear; one through the inside is blocked
    assert not _hidden_from_all(np.array([[0, 0]]), np.array([2, 2]), [(0, 2, 0, 3)])
    assert _hidden_from_all(np.array([[0, 0]]), np.array([0, 5]), [(0, 2, 0, 2)])


def test_noise_streams_are_uniform_and_fixed_by_their_seed():
    u = noise_uniforms(12345, 120, 3)
    assert u.shape == (121, 3) and u.dtype == np.float64
    assert (u > 0).all() and (u < 1).all() and abs(u.mean() - 0.5) < 0.05
    assert np.array_equal(u, noise_uniforms(12345, 120, 3))
    assert not np.array_equal(u, noise_uniforms(12346, 120, 3))
    other_run = noise_uniforms(12345, 120, 3, run=1)  # another Monte Carlo run of the same episode
    assert np.array_equal(other_run, noise_uniforms(12345, 120, 3, run=1))
    assert not np.array_equal(u, other_run)
    with pytest.raises(ValueError, match="run must be an integer >= 0"):
        noise_uniforms(1, 5, 1, run=-1)
    # The stream is numpy's PCG64 raw output, which numpy keeps stable across versions.
    raw = np.random.PCG64(12345).random_raw(1)[0]
    assert u[0, 0] == ((int(raw) >> 11) + 0.5) / 2.0**53


# ------------------------------------------------------------------ the frozen sets


@pytest.mark.parametrize("name", sorted(FROZEN))
def test_frozen_sets_load_with_their_hash_and_obey_the_rules(name):
    loaded, digest = load_file(SETS_DIR / name)
    assert digest == FROZEN[name]
    grid, agents = int(name[1:3]), int(name[5])
    assert {(s.grid, s.agents, s.max_steps) for s in loaded} == {(grid, agents, 120)}
    assert [s.id for s in loaded] == [f"obs{k}-{n}" for k in range(8) for n in SNR_BINS]
    for s in loaded:
        assert len(s.episodes) == 200 and s.file_sha256 == digest
        assert s.sha256 == set_digest(s.id, grid, agents, 120, s.episodes)
        for i, e in enumerate(s.episodes[:: 7]):  # a spread of each set (every rule on every episode is slow)
            _check_rules(e, grid, s.obstructions, s.snr, (7 * i) % 4)


def test_a_frozen_set_is_what_the_generator_draws_from_its_seed():
    (frozen,) = load_sets(20, 1, obstructions=[3], snrs=["medium"])
    drawn, _ = generate_set(20, 1, 3, "medium", episodes=200)
    assert set_digest("obs3-medium", 20, 1, 120, drawn) == frozen.sha256


def _tamper(text: str) -> str:
    """The same file with one episode's strength changed by 0.01 counts/s."""
    at = text.index('"S":') + 4
    end = text.index(",", at)
    return text[:at] + f"{float(text[at:end]) + 0.01:.2f}" + text[end:]


def test_a_changed_set_file_is_refused(tmp_path, monkeypatch):
    original = SETS_DIR / "g20-a1.json"
    copy = tmp_path / "g20-a1.json"
    shutil.copy(original, copy)
    assert load_file(copy, sha256=FROZEN["g20-a1.json"])[1] == FROZEN["g20-a1.json"]
    copy.write_text(_tamper(original.read_text()))
    with pytest.raises(SetFileError, match=r"was changed: its SHA-256 is .* expected"):
        load_file(copy, sha256=FROZEN["g20-a1.json"])
    # Without a hash to check the bytes against, the set's own digest refuses the changed episode.
    with pytest.raises(SetFileError, match=r"obs0-low .* does not match its digest"):
        load_file(copy)
    # A frozen file is always checked against FROZEN, whoever asks for it.
    monkeypatch.setattr(sets, "SETS_DIR", tmp_path)
    with pytest.raises(SetFileError, match="git checkout"):
        load_sets(20, 1)
    with pytest.raises(SetFileError, match="no frozen sets for grid 20 with 2 agent"):
        load_sets(20, 2)


def test_a_malformed_set_file_says_what_is_wrong(tmp_path):
    doc = json.loads((SETS_DIR / "g20-a1.json").read_text())
    doc["sets"][0]["episodes"][0]["src"] = [20, 3]
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(SetFileError, match=r"set obs0-low: malformed episode: a cell is \[row, col\]"):
        load_file(path)
    doc = json.loads((SETS_DIR / "g20-a1.json").read_text())
    two = next(s for s in doc["sets"] if s["obstructions"] == 2)
    first = two["episodes"][0]["obs"][0]
    two["episodes"][0]["obs"][1] = [first[2] + 1, first[1], first[2] + 2, first[3]]  # right below it
    path.write_text(json.dumps(doc))
    with pytest.raises(SetFileError, match=r"touch or overlap: .* keep at least one free cell"):
        load_file(path)
    path.write_text("{not json")
    with pytest.raises(SetFileError, match="is not JSON"):
        load_file(path)
    with pytest.raises(SetFileError, match="cannot read"):
        load_file(tmp_path / "absent.json")


def test_a_head_of_a_set_is_balanced_over_the_snr_subbins():
    (s,) = load_sets(20, 3, obstructions=[7], snrs=["high"])
    head = s.head(8)
    assert head.id == "obs7-high[:8]" and head.episodes == s.episodes[:8] and head.sha256 == s.sha256
    edges = subbin_edges("high")
    for i, e in enumerate(head.episodes):
        assert edges[i % 4] < max(e.snrs()) <= edges[i % 4 + 1]


def test_a_part_of_a_set_keeps_each_episodes_index_and_says_which_it_is():
    (s,) = load_sets(20, 3, obstructions=[7], snrs=["high"])
    part = s.part(40, 60)
    assert part.id == "obs7-high[40:100]" and part.episodes == s.episodes[40:100]
    assert part.first == 40 and part.sha256 == s.sha256
    assert s.part(0, 12).id == s.head(12).id == "obs7-high[:12]" and s.part(0) is s
    assert s.part(190).id == "obs7-high[190:200]" and len(s.part(190, 50).episodes) == 10
    for bad, message in (((200, 4), "first episode must be 0..199"), ((-1, 4), "first episode"),
                         ((4, 0), "at least one episode")):
        with pytest.raises(ValueError, match=message):
            s.part(*bad)
    with pytest.raises(ValueError, match="already a part"):
        part.part(0, 4)


# ------------------------------------------------------------------ metrics


def _r(i: int, length: int, success: bool, **kw) -> EpisodeResult:
    return EpisodeResult("obs0-low", i, length, success, **kw)


def test_summary_on_a_hand_computed_case():
    rows = [_r(0, 10, True, declared_step=4, declared_error_m=1.0, track_rmse_m=2.0),
            _r(1, 20, True, track_rmse_m=4.0),
            _r(2, 30, True, declared_step=8, declared_error_m=0.0, track_rmse_m=6.0),
            _r(3, 120, False, declared_step=50, declared_error_m=3.0),
            _r(4, 120, False)]
    s = summarize(rows, 120)
    assert (s["episodes"], s["completed"], s["completion_rate"]) == (5, 3, 0.6)
    assert s["median_completed_length"] == 20.0 and s["median_ci95"] == [None, None]  # n = 3: no 95% interval
    assert s["mean_length"] == 60.0
    sd = math.sqrt(sum((x - 60) ** 2 for x in (10, 20, 30, 120, 120)) / 4)
    assert s["mean_length_ci95"] == pytest.approx(t95(4) * sd / math.sqrt(5))
    assert s["completed_p2_5"] == pytest.approx(10.5) and s["completed_p97_5"] == pytest.approx(29.5)
    assert (s["declared"], s["declared_correct"]) == (3, 2)
    assert s["declared_error_m_mean"] == pytest.approx(4 / 3) and s["declared_step_median"] == 8.0
    assert s["track_rmse_m_mean"] == 4.0
    lo, hi = s["completion_ci95"]
    assert lo == pytest.approx(0.2307, abs=1e-3) and hi == pytest.approx(0.8824, abs=1e-3)
    assert summarize([], 120)["completion_rate"] is None


def test_median_interval_from_order_statistics():
    # n = 10: P(Bin(10, 1/2) <= 1) = 11/1024, so [x_(2), x_(9)] covers the median with 97.9%.
    assert median_ci([5, 1, 9, 3, 7, 2, 8, 4, 10, 6]) == (2.0, 9.0)
    assert median_ci(range(1, 7)) == (1.0, 6.0)  # n = 6: the extremes, 96.9%
    assert all(math.isnan(v) for v in median_ci(range(5)))  # n = 5 cannot reach 95%
    lo, hi = median_ci(range(1, 101))  # n = 100: the 40th and 61st values
    assert (lo, hi) == (40.0, 61.0)
    assert all(math.isnan(v) for v in wilson(0, 0))


def test_paired_comparison_on_hand_episodes():
    a = [_r(0, 10, True), _r(1, 120, False), _r(2, 30, True), _r(3, 5, True)]
    b = [_r(0, 20, True), _r(1, 50, True), _r(2, 30, True), _r(3, 9, True)]
    c = paired(a, b, 120)
    assert (c["wins"], c["losses"], c["ties"]) == (2, 1, 1)
    assert c["mean_diff"] == pytest.approx((-10 + 70 + 0 - 4) / 4) and c["median_diff"] == -2.0
    split = ("both_completed", "only_a_completed", "only_b_completed", "neither_completed")
    assert tuple(c[k] for k in split) == (3, 0, 1, 0)
    assert c["sign_test_p"] == pytest.approx(1.0)
    assert sign_test(9, 1) == pytest.approx(2 * 11 / 1024)
    with pytest.raises(ValueError, match="same episodes"):
        paired(a, b[::-1], 120)
