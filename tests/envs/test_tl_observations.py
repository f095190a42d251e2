"""Target-localization observation variants: the source posterior against a hand computation, the
estimate map, the posterior map, the ego windows, and one builder giving the same observations at any
batch size."""

from __future__ import annotations

import math

import pytest
import torch
from medc_training.envs import make_batched, make_env
from medc_training.envs.observation import MAX_NAME_LENGTH
from medc_training.envs.target_localization import (
    BACKGROUND,
    SOURCE_STRENGTH,
    WALL_ATTENUATION,
    sensor_reading,
)
from medc_training.envs.tl_observation import (
    LOG_FLOOR,
    ObservationSpec,
    SourceEstimator,
    TeamMemory,
    observation_channels,
    observation_shape,
    observe,
    parse_observation,
)

VARIANTS = ("maps", "maps+estimate", "ego3", "ego4+estimate", "ego9+estimate", "maps+posterior",
            "ego6+estimate+posterior")


def hand_posterior(grid, wall_col, visits):
    """Poisson posterior over source cells, in float64 plain Python, for a full-height wall in
    column ``wall_col`` (None: no wall): a line between cells on opposite sides crosses it once."""
    logp = {}
    for sr in range(grid):
        for sc in range(grid):
            if sc == wall_col or any((sr, sc) == p for p, _ in visits):
                continue
            total = 0.0
            for (pr, pc), r in visits:
                crossed = wall_col is not None and (pc - wall_col) * (sc - wall_col) < 0
                d2 = (pr - sr) ** 2 + (pc - sc) ** 2
                rate = SOURCE_STRENGTH * WALL_ATTENUATION ** int(crossed) / (1 + d2)
                rate += BACKGROUND
                total += r * math.log(rate) - rate
            logp[(sr, sc)] = total
    top = max(logp.values())
    weights = {c: math.exp(v - top) for c, v in logp.items()}
    z = sum(weights.values())
    return {c: w / z for c, w in weights.items()}


@pytest.mark.parametrize("wall_col", [None, 3])
@pytest.mark.parametrize("noise", [False, True])
def test_posterior_equals_hand_computed_poisson_posterior(wall_col, noise):
    grid = 6
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    if wall_col is not None:
        walls[0, :, wall_col] = True
    target = torch.tensor([[1, 4 if wall_col is not None else 2]])
    path = [[(4, 0), (5, 5)], [(3, 1), (5, 4)], [(2, 1), (4, 5)]]
    gen = torch.Generator().manual_seed(3)
    est = SourceEstimator(grid, "cpu")
    log_post = est.prior(walls)
    visits = []
    for cells in path:
        pos = torch.tensor([cells])
        r = sensor_reading(pos, target, walls, noise=noise, generator=gen)
        est.update(log_post, walls, pos, r)
        visits += [(c, float(v)) for c, v in zip(cells, r[0].tolist())]
    if noise:
        assert all(v == int(v) for _, v in visits)  # Poisson counts
    got = est.posterior(log_post)[0].view(grid, grid)
    want = hand_posterior(grid, wall_col, visits)
    for (r, c), p in want.items():
        assert got[r, c].item() == pytest.approx(p, abs=1e-5)
    # Walls and visited cells are not the source; probabilities sum to one.
    for (r, c), _ in visits:
        assert got[r, c] == 0.0
    if wall_col is not None:
        assert float(got[:, wall_col].sum()) == 0.0
    assert float(got.sum()) == pytest.approx(1.0, abs=1e-5)
    if not noise:
        assert int(got.flatten().argmax()) == int(target[0, 0] * grid + target[0, 1])


def test_estimate_map_is_one_minus_expected_chebyshev_moves():
    grid = 5
    est = SourceEstimator(grid, "cpu")
    log_post = torch.full((1, grid * grid), LOG_FLOOR)
    log_post[0, 0 * grid + 4] = math.log(0.25)  # p(0,4) = 1/4
    log_post[0, 3 * grid + 1] = math.log(0.75)  # p(3,1) = 3/4
    emap = est.estimate_map(log_post)[0]
    for r in range(grid):
        for c in range(grid):
            e = 0.25 * max(abs(r - 0), abs(c - 4)) + 0.75 * max(abs(r - 3), abs(c - 1))
            assert emap[r, c].item() == pytest.approx(1 - e / (grid - 1), abs=1e-6)


def test_a_mismatched_sensor_never_leaves_the_team_without_a_candidate():
    grid = 5
    est = SourceEstimator(grid, "cpu")
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    log_post = est.prior(walls)
    for value in [1e6] * 20 + [3e38, float("inf"), float("nan")]:  # readings no source could produce
        est.update(log_post, walls, torch.tensor([[[2, 2]]]), torch.tensor([[value]]))
        p = est.posterior(log_post)
        assert torch.isfinite(p).all() and float(p.sum()) == pytest.approx(1.0, abs=1e-5)
        assert torch.isfinite(est.estimate_map(log_post)).all()


def test_names_round_trip_and_bad_names_say_what_is_allowed():
    for name in ("maps", "maps+estimate", "ego1", "ego12+estimate"):
        assert parse_observation(name).name == name
        assert parse_observation({"name": name}) == parse_observation(name)
    assert observation_shape("ego6+estimate", 13) == (5, 13, 13)
    assert observation_shape("maps+estimate", 13) == (6, 13, 13)
    for bad in ("ego0", "ego", "maps+", "ego-3", "egocentric", "x" * 100, 7):
        with pytest.raises(ValueError, match="observation"):
            parse_observation(bad)
    # A window wider than the grid is allowed: off-grid cells read as walls.
    env = make_batched("target_localization", grid=6, walls=0, agents=1, observation="ego8")
    assert env.reset()[0].shape == (1, 1, 4, 17, 17)


def test_posterior_names_round_trip_in_their_one_order():
    for name in ("maps+posterior", "maps+estimate+posterior", "ego1+posterior", "ego6+estimate+posterior"):
        spec = parse_observation(name)
        assert spec.posterior and spec.name == name
        assert parse_observation({"name": name}) == spec
    assert parse_observation("ego6+estimate+posterior") == ObservationSpec("ego", 6, True, True)
    assert ObservationSpec("ego", 6, True) == parse_observation("ego6+estimate")  # posterior: False
    assert len("ego255+estimate+posterior") <= MAX_NAME_LENGTH  # the longest name is read
    assert parse_observation("ego255+estimate+posterior").radius == 255
    assert observation_shape("ego6+estimate+posterior", 13) == (6, 13, 13)
    assert observation_shape("maps+estimate+posterior", 13) == (7, 13, 13)
    assert observation_channels("ego6+estimate+posterior")[-2:] == ("source_estimate", "source_posterior")
    assert observation_channels("maps+posterior")[-2:] == ("walls", "source_posterior")
    for bad in ("ego6+posterior+estimate", "maps+posterior+posterior", "ego6+posteriors", "posterior"):
        with pytest.raises(ValueError, match=r"egoR\+estimate\+posterior") as refused:
            parse_observation(bad)
        assert "'maps+posterior'" in str(refused.value)
    with pytest.raises(ValueError, match=r"name such as .*ego6\+estimate\+posterior"):
        parse_observation("ego6+estimate+posterior" + "+posterior" * 2)  # past the length read


def test_ego_window_centres_the_agent_and_walls_the_outside():
    grid, r = 5, 2
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    walls[0, 1, 2] = True
    pos = torch.tensor([[[0, 0], [0, 1]]])
    mem = TeamMemory(ObservationSpec("ego", r, True), 1, grid, "cpu")
    mem.start(walls, pos, sensor_reading(pos, torch.tensor([[4, 4]]), walls))
    obs = mem.observe(pos, walls)
    assert obs.shape == (1, 2, 5, 5, 5)
    a0 = obs[0, 0]
    # Agent 0 at (0,0): window rows/cols -2..2; off-grid cells are walls, the rest is the grid.
    assert a0[0, :2].eq(1).all() and a0[0, :, :2].eq(1).all()
    assert a0[0, 2 + 1, 2 + 2] == 1.0 and a0[0, 2:, 2:].sum() == 1.0  # the wall at (1,2)
    assert a0[1].sum() == 1.0 and a0[1, 2, 3] == 1.0  # the other agent, one column east
    assert a0[1, 2, 2] == 0.0  # itself is not in the team channel
    assert a0[2, 2, 2] > 0 and a0[3, 2, 2] == pytest.approx(0.1)  # own reading, one visit
    assert (a0[4, :2] == 0).all()  # off-grid estimate reads 0
    full = mem.estimate_map()[0]
    assert a0[4, 2:, 2:].tolist() == full[:3, :3].tolist()


def _hand_made_posterior(mem, walls, modes, half, ruled_out):
    """Give ``mem`` (one episode, known strength and background) a posterior of weight 1 at each of
    ``modes``, 1/2 at ``half``, ~0 on every other free cell and 0 on walls and ``ruled_out``."""
    g = mem.grid
    log_post = torch.full((1, g * g), -40.0)
    for r, c in modes:
        log_post[0, r * g + c] = 0.0
    log_post[0, half[0] * g + half[1]] = math.log(0.5)
    for r, c in ruled_out:
        log_post[0, r * g + c] = LOG_FLOOR
    log_post[0, walls[0].flatten()] = LOG_FLOOR
    mem.log_post = log_post


def test_posterior_channel_reads_the_posterior_over_its_mode():
    """1 at each mode, p/max elsewhere, 0 on walls and ruled-out cells; in an ego window 0 off the grid,
    and the grid cells are those of the absolute map."""
    grid, r = 6, 2
    walls = torch.zeros((1, grid, grid), dtype=torch.bool)
    walls[0, 3, 1:4] = True
    pos = torch.tensor([[[0, 0], [5, 5]]])
    modes, half, ruled_out = [(1, 4), (5, 0)], (2, 2), [(0, 0), (5, 5)]
    ego = TeamMemory(parse_observation("ego2+estimate+posterior"), 1, grid, "cpu")
    maps = TeamMemory(parse_observation("maps+posterior"), 1, grid, "cpu")
    for mem in (ego, maps):
        mem.start(walls, pos, sensor_reading(pos, torch.tensor([[1, 4]]), walls))
        _hand_made_posterior(mem, walls, modes, half, ruled_out)
    full = maps.observe(pos, walls.float())[0, 0, 5]
    assert full.shape == (grid, grid) and torch.equal(full, maps.posterior_map()[0])
    assert float(full.min()) >= 0.0 and float(full.max()) == 1.0
    for r_, c_ in modes:
        assert full[r_, c_] == 1.0
    assert full[half] == pytest.approx(0.5, rel=1e-6)
    assert full[walls[0]].eq(0).all()
    for cell in ruled_out:
        assert full[cell] == 0.0
    assert int((full == 1.0).sum()) == 2 and bool((full[full < 1.0] <= 0.5 + 1e-6).all())
    obs = ego.observe(pos, walls.float())
    assert obs.shape == (1, 2, 6, 5, 5)
    a0, a1 = obs[0, 0, 5], obs[0, 1, 5]  # agent 0 at (0,0), agent 1 at (5,5)
    assert a0[:r].eq(0).all() and a0[:, :r].eq(0).all()  # off the grid: 0
    assert torch.equal(a0[r:, r:], full[:r + 1, :r + 1])
    assert a1[r + 1:].eq(0).all() and a1[:, r + 1:].eq(0).all()
    assert torch.equal(a1[:r + 1, :r + 1], full[grid - r - 1:, grid - r - 1:])
    assert a0[r, r] == 0.0 and a1[r, r] == 0.0  # the ruled-out cells the agents stand on


def test_a_memory_without_a_posterior_has_no_posterior_map():
    assert TeamMemory(parse_observation("ego3"), 1, 5, "cpu").posterior_map() is None
    assert TeamMemory(parse_observation("maps+posterior"), 1, 5, "cpu").estimator is not None


def _replay_memories(variant, batch):
    return [TeamMemory(parse_observation(variant), 1, 12, "cpu") for _ in range(batch)]


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("batch", [1, 5])
def test_core_observations_equal_a_replay_from_scratch_at_any_batch_size(variant, batch):
    env = make_batched("target_localization", num_envs=batch, seed=11, agents=3, walls=2, grid=12,
                       max_steps=12, noise=True, observation=variant)
    obs, mask = env.reset()
    assert tuple(obs.shape[2:]) == observation_shape(variant, 12)
    memories = _replay_memories(variant, batch)
    for b, m in enumerate(memories):
        m.start(env.walls[b:b + 1], env.positions[b:b + 1], env.readings[b:b + 1])
        assert torch.equal(m.observe(env.positions[b:b + 1], env.walls[b:b + 1])[0], obs[b])
    gen = torch.Generator().manual_seed(0)
    resets = 0
    for _ in range(30):
        actions = torch.multinomial(mask.view(-1, 8).float(), 1, generator=gen).view(batch, 3)
        out = env.step(actions)
        for b, m in enumerate(memories):
            sl = slice(b, b + 1)
            if out.done[b]:
                m.start(env.walls[sl], env.positions[sl], env.readings[sl])
                resets += 1
            else:
                m.record(env.walls[sl], env.positions[sl], env.readings[sl])
            assert torch.equal(m.observe(env.positions[sl], env.walls[sl])[0], out.obs[b]), (variant, b)
            for i in range(3):  # one agent's view, as its node builds it
                assert torch.equal(m.observe_agent(env.positions[sl], env.walls[sl], i)[0], out.obs[b, i])
        mask = out.mask
    assert resets > 0


@pytest.mark.parametrize("variant", ["ego9+estimate+posterior", "ego4+estimate+posterior+information",
                                     "maps"])
def test_one_agents_view_equals_its_row_of_the_teams_views(variant):
    """observe_agent builds an agent's window from a padded grid: the same values as observe's row,
    at every batch row, for agents on the edges and corners (off-grid cells a wall) and on a shared
    cell (the team channel counts only the others)."""
    env = make_batched("target_localization", num_envs=4, seed=3, agents=3, walls=1, grid=9, max_steps=40,
                       observation=variant)
    env.reset()
    corners = torch.tensor([[[0, 0], [8, 8], [0, 8]], [[4, 4], [4, 4], [8, 0]],
                            [[0, 3], [5, 8], [8, 2]], [[1, 1], [7, 7], [1, 1]]])
    walls = env.walls.clone()
    walls[torch.arange(4).view(4, 1), corners[..., 0], corners[..., 1]] = False  # the team on free cells
    assert bool(walls.any()), "the views must show walls"
    m = env.memory
    team = m.observe(corners, walls)
    for i in range(3):
        assert torch.equal(m.observe_agent(corners, walls, i), team[:, i]), (variant, i)


@pytest.mark.parametrize("variant", ["maps+estimate", "ego5+estimate", "ego6+estimate+posterior"])
def test_pettingzoo_env_gives_the_core_observations(variant):
    env = make_env("target_localization", seed=4, agents=2, walls=1, grid=10, max_steps=20,
                   observation=variant)
    core = make_batched("target_localization", num_envs=1, seed=4, agents=2, walls=1, grid=10, max_steps=20,
                        observation=variant)
    obs, _ = env.reset(seed=4)
    ref, mask = core.reset(seed=4)
    for _ in range(15):
        for i, agent in enumerate(env.agents):
            assert torch.equal(torch.from_numpy(obs[agent]["observation"]), ref[0, i])
        actions = [int(mask[0, i].nonzero()[0]) for i in range(2)]
        obs, *_ = env.step({a: actions[i] for i, a in enumerate(env.agents)})
        out = core.step(torch.tensor([actions]))
        ref, mask = out.obs, out.mask
        if not env.agents:
            break


def test_observe_requires_the_estimate_when_the_variant_shows_it():
    pos = torch.zeros((1, 1, 2), dtype=torch.long)
    maps = torch.zeros((1, 5, 5))
    with pytest.raises(ValueError, match="needs the source estimate"):
        observe(parse_observation("ego2+estimate"), pos, maps, maps, maps)
    with pytest.raises(ValueError, match="needs the source posterior map"):
        observe(parse_observation("ego2+estimate+posterior"), pos, maps, maps, maps, maps)
    with pytest.raises(ValueError, match="needs the source posterior map"):
        observe(parse_observation("maps+posterior"), pos, maps, maps, maps)


@pytest.mark.parametrize(("grid", "walls"), [(5, 0), (5, 1), (13, 3), (22, 4), (30, 5), (33, 2)])
def test_rates_from_every_cell_equal_the_sensor_model_bit_for_bit(grid, walls):
    """Sampling every line, and the crossing tables (the walls as segments, grids up to 32x32; 33x33
    has none) with the (walls crossed, d²) rate table the team memory looks up, give exactly the
    simulator's noise-free readings for every candidate source cell, from sensors on every free cell
    of several layouts."""
    from medc_training.envs.target_localization import (
        expected_rate_from_sources,
        generate_layouts,
        rates_from_every_cell,
    )
    from medc_training.envs.tl_sensing import sampled_rate_table, segment_crossings, wall_segments

    lay = generate_layouts(6, grid, walls, 3, torch.Generator().manual_seed(grid), torch.device("cpu"))
    idx = torch.arange(grid * grid)
    every = torch.stack((idx // grid, idx % grid), dim=-1)
    got = rates_from_every_cell(lay["positions"], lay["walls"])
    assert torch.equal(got, expected_rate_from_sources(lay["positions"], every, lay["walls"]))
    segments, ok = wall_segments(lay["walls"], max(1, walls))
    assert bool(ok.all())
    sensors = every[::3].unsqueeze(0).expand(6, -1, -1)  # a third of the cells, walls included
    crossed = segment_crossings(sensors, segments, grid)
    if grid > 32:
        assert crossed is None
    else:
        dist2 = ((sensors.unsqueeze(2) - every) ** 2).sum(-1)  # [B,N,G²]
        rate = sampled_rate_table(grid, segments.shape[1], torch.device("cpu"))[0]
        looked_up = rate[crossed * (2 * (grid - 1) ** 2 + 1) + dist2]
        assert torch.equal(looked_up, expected_rate_from_sources(sensors, every, lay["walls"]))
    # ... and column s is what sensor_reading returns with the source at cell s.
    s = int(lay["target"][0, 0] * grid + lay["target"][0, 1])
    direct = sensor_reading(lay["positions"][:1], lay["target"][:1], lay["walls"][:1])
    assert torch.equal(got[0, :, s], direct[0])


def test_wall_segments_accept_only_maps_made_of_non_touching_thin_segments():
    """The crossing tables count segments met, which equals the sampled rule's count of wall runs
    only for one-cell-thick segments that never touch; any other map takes the sampled path."""
    from medc_training.envs.tl_sensing import wall_segments

    walls = torch.zeros((5, 9, 9), dtype=torch.bool)
    walls[0, 2, 1:5] = True  # one horizontal segment
    walls[0, 5:8, 7] = True  # and one vertical
    walls[1, 2:4, 2:4] = True  # a 2x2 block
    walls[2, 2, 1:5] = True
    walls[2, 3, 5] = True  # touches the first diagonally
    walls[3, 2, 1:5] = True
    walls[3, 2:6, 4] = True  # an L
    for c in range(0, 9, 2):  # five segments: more than the slots asked for
        walls[4, 0:2, c] = True
    segments, ok = wall_segments(walls, 4)
    assert ok.tolist() == [True, False, False, False, False]
    assert segments.shape == (5, 4, 4)
    assert sorted(segments[0, :2].tolist()) == [[2, 1, 2, 4], [5, 7, 7, 7]]
    assert segments[0, 2:].tolist() == [[-1, -1, -2, -2]] * 2
    assert wall_segments(walls[4:], 5)[1].tolist() == [True]


def test_team_memory_falls_back_to_sampling_for_maps_not_made_of_segments():
    """An operator's own map (here a 2x2 block, which the sampled rule counts as one run) gives the
    posterior of the sampled rule, not of the crossing tables."""
    walls = torch.zeros((2, 9, 9), dtype=torch.bool)
    walls[:, 4:6, 4:6] = True
    pos = torch.tensor([[[1, 1], [8, 8], [1, 8]]] * 2)
    spec = parse_observation("ego3+estimate")
    mem = TeamMemory(spec, 2, 9, "cpu", posterior=True, max_walls=2)
    readings = sensor_reading(pos, torch.tensor([[7, 7]] * 2), walls)
    mem.start(walls, pos, readings)
    assert not bool(mem.segments_ok.any())
    expected = mem.estimator.prior(walls)
    mem.estimator.update(expected, walls, pos, readings)  # no segments: every line sampled
    assert torch.equal(mem.log_post, expected)


@pytest.mark.parametrize("sensing", ["paper-simple", "realistic"])
def test_ruled_out_cells_are_those_within_the_success_radius(sensing):
    """The stencil ruled_out marks exactly the cells some agent's d² puts within reach (corners
    and edges included)."""
    est = SourceEstimator(9, "cpu", sensing)
    gen = torch.Generator().manual_seed(3)
    pos = torch.randint(0, 9, (64, 3, 2), generator=gen)
    pos[0, 0] = torch.tensor([0, 0])
    pos[1, 1] = torch.tensor([8, 8])
    pos[2, 2] = torch.tensor([0, 8])
    expected = est.sensing.within_reach(est.dist2(pos)).any(1)
    assert torch.equal(est.ruled_out(pos), expected)
    assert int(expected[0].sum()) >= 1
