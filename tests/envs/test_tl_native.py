"""The estimator's native kernel (``tl_native.c``) against the torch path it stands in for: hand cases
and 100-step traces of both presets within the stated tolerance, the same ruled-out zeros, batch-size
independence; the build cache, the fallback to torch and the checks on bad input."""

from __future__ import annotations

import contextlib

import pytest
import torch
from env_scenarios import estimator_trace
from medc_training.envs import tl_native
from medc_training.envs.tl_observation import LOG_FLOOR, SourceEstimator
from medc_training.envs.tl_sensing import parse_sensing, wall_segments

#: The stated tolerance between the kernel and the torch fused path (docs/environments.md, "Speed"):
#: max abs difference of posterior probabilities and of observation values over a trace.
POSTERIOR_TOLERANCE = 1e-3
OBSERVATION_TOLERANCE = 1e-4


@pytest.fixture(scope="module", autouse=True)
def _kernel_built() -> None:
    """These tests measure the kernel itself: the machine that runs them has a C compiler."""
    assert tl_native.enabled() and tl_native.library() is not None


def _steps(est: SourceEstimator, native: bool, readings, walls,
           monkeypatch) -> tuple[torch.Tensor, torch.Tensor]:
    monkeypatch.setenv("MEDC_NATIVE", "1" if native else "0")
    log_post = est.prior(walls)
    post = torch.empty((walls.shape[0], est.grid * est.grid))
    for positions, counts in readings:
        assert est.update(log_post, walls, positions, counts, posterior_out=post)
    return log_post.clone(), post


@pytest.mark.parametrize("levels", [[4, 3], [12, 16], [3, 2], [5, 7]])
def test_the_kernel_equals_the_torch_path_on_hand_cases(levels, monkeypatch) -> None:
    grid = 9
    sensing = parse_sensing({"name": "realistic", "levels": levels})
    est = SourceEstimator(grid, "cpu", sensing, path="fused")
    walls = torch.zeros((2, grid, grid), dtype=torch.bool)
    walls[1, 4, 2:7] = True  # one episode with a wall between the readings
    nan = float("nan")
    readings = [
        (torch.tensor([[[0, 0], [8, 8]], [[0, 4], [8, 4]]]), torch.tensor([[40.0, 14.0], [22.0, 9.0]])),
        (torch.tensor([[[3, 1], [5, 2]], [[2, 2], [6, 6]]]), torch.tensor([[75.0, 30.0], [0.0, 1e9]])),
        (torch.tensor([[[7, 1], [1, 7]], [[0, 8], [8, 0]]]), torch.tensor([[nan, 3.0], [5.0, 18.0]])),
    ]
    got_log, got = _steps(est, True, readings, walls, monkeypatch)
    want_log, want = _steps(est, False, readings, walls, monkeypatch)
    assert float((got - want).abs().max()) < 1e-5
    assert torch.equal(got == 0, want == 0)  # the ruled-out cells and the walls: exact zeros in both
    assert float((got_log - want_log).abs().max()) < 1e-3
    assert float(got_log.amax((1, 2)).abs().max()) == 0.0 and float(got_log.min()) >= LOG_FLOOR
    assert float(got.sum(1).sub(1).abs().max()) < 1e-5
    # The marginal of a kept posterior, read again without an update.
    monkeypatch.setenv("MEDC_NATIVE", "1")
    assert float((est.posterior(got_log) - got).abs().max()) < 1e-6


def test_the_one_level_kernel_equals_the_torch_path_on_hand_cases() -> None:
    """Paper-simple: walls crossed from the crossing tables and the segments, rates looked up (the log
    posterior bit for bit the torch path's), the posterior written in the same pass."""
    grid = 12
    est = SourceEstimator(grid, "cpu", "paper-simple", path="fused")
    walls = torch.zeros((3, grid, grid), dtype=torch.bool)
    walls[0, 5, 2:9] = True  # a horizontal wall
    walls[1, 1:7, 6] = True  # a vertical one
    walls[1, 9, 1:4] = True
    segments, ok = wall_segments(walls, 2)
    assert bool(ok.all())
    runs = {}
    for native in (True, False):
        gen = torch.Generator().manual_seed(1)
        log_post, post = est.prior(walls), torch.empty((3, grid * grid))
        with contextlib.nullcontext() if native else tl_native.turned_off():
            for step in range(6):
                positions = torch.randint(0, grid, (3, 2, 2), generator=torch.Generator().manual_seed(step))
                positions[..., 0].clamp_(max=4)  # above the walls: free cells
                counts = torch.poisson(torch.full((3, 2), 40.0), generator=gen)
                assert est.update(log_post, walls, positions, counts, segments=segments,
                                  posterior_out=post) == native
            runs[native] = (log_post, post if native else est.posterior(log_post))
    (got_log, got), (want_log, want) = runs[True], runs[False]
    assert torch.equal(got_log, want_log)  # the torch path's arithmetic in its order
    assert float((got - want).abs().max()) < 1e-6
    assert torch.equal(got == 0, want == 0)
    assert bool((got.view(3, grid, grid)[walls] == 0).all())


def test_the_expected_distance_kernel_equals_the_torch_arithmetic() -> None:
    grid = 17
    est = SourceEstimator(grid, "cpu", "realistic", path="fused")
    p = torch.rand((5, grid * grid), generator=torch.Generator().manual_seed(3)) ** 8
    p[0] = 0.0
    p[0, 40] = 1.0  # sure of one cell: E is the Chebyshev distance to it
    p /= p.sum(1, keepdim=True)
    got = est.expected_from_posterior(p)
    with tl_native.turned_off():
        want = est.expected_from_posterior(p)
    assert float((got - want).abs().max()) < 1e-4
    rows, cols = torch.arange(grid).repeat_interleave(grid), torch.arange(grid).repeat(grid)
    chebyshev = torch.maximum((rows - 40 // grid).abs(), (cols - 40 % grid).abs()).float()
    assert float((got[0] - chebyshev).abs().max()) < 1e-5


@pytest.mark.parametrize(("sensing", "grid"), [("realistic", 14), ("paper-simple", 13)])
def test_a_100_step_trace_on_the_kernel_agrees_with_the_torch_path(sensing, grid) -> None:
    native = estimator_trace(sensing, grid, "fused", batch=16)
    with tl_native.turned_off():
        torch_path = estimator_trace(sensing, grid, "fused", batch=16)
    assert all(torch.equal(f[2], r[2]) for f, r in zip(native, torch_path, strict=True))  # same episodes
    d_obs = max(float((f[0] - r[0]).abs().max()) for f, r in zip(native, torch_path, strict=True))
    d_post = max(float((f[1] - r[1]).abs().max()) for f, r in zip(native, torch_path, strict=True))
    assert d_post <= POSTERIOR_TOLERANCE and d_obs <= OBSERVATION_TOLERANCE
    # A zero in one path is at most a dead cell's mass in the other.
    for f, r in zip(native, torch_path, strict=True):
        assert bool((r[1][f[1] == 0] < 1e-30).all()) and bool((f[1][r[1] == 0] < 1e-30).all())
    assert d_post > 0.0  # the kernel did run: its rounding is not torch's


def test_one_episode_gets_the_same_posterior_at_any_batch_size(monkeypatch) -> None:
    monkeypatch.setenv("MEDC_NATIVE", "1")
    grid, batch = 11, 5
    est = SourceEstimator(grid, "cpu", "realistic", path="fused")
    gen = torch.Generator().manual_seed(2)
    walls = torch.zeros((batch, grid, grid), dtype=torch.bool)
    together, alone = est.prior(walls), [est.prior(walls[:1]) for _ in range(batch)]
    for _ in range(6):
        positions = torch.randint(0, grid, (batch, 3, 2), generator=gen)
        counts = torch.poisson(torch.full((batch, 3), 25.0), generator=gen)
        est.update(together, walls, positions, counts)
        for b in range(batch):
            est.update(alone[b], walls[:1], positions[b:b + 1], counts[b:b + 1])
    for b in range(batch):
        assert torch.equal(together[b], alone[b][0])


def test_the_library_is_cached_under_its_sources_hash(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MEDC_NATIVE_CACHE", str(tmp_path))
    path = tl_native.build()
    assert path.parent == tmp_path and path.exists() and path.name.startswith("tl_native-")
    stamp = path.stat().st_mtime_ns
    assert tl_native.build() == path and path.stat().st_mtime_ns == stamp  # kept, not rebuilt
    edited = tmp_path / "tl_native.c"
    edited.write_text(tl_native.SOURCE.read_text() + "\n/* edited */\n")
    monkeypatch.setattr(tl_native, "SOURCE", edited)
    assert tl_native.library_path() != path  # an edited kernel is another library
    assert tl_native.main([]) == 0 and tl_native.library_path().exists()


def test_without_a_compiler_or_with_native_off_the_torch_path_runs(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MEDC_NATIVE", "0")
    assert tl_native.library() is None and not tl_native.usable(torch.zeros(2))
    monkeypatch.setenv("MEDC_NATIVE", "1")
    monkeypatch.setenv("MEDC_NATIVE_CACHE", str(tmp_path))  # nothing built here yet
    monkeypatch.setattr(tl_native, "_compiler", lambda: None)
    monkeypatch.setattr(tl_native, "_lib", None)
    monkeypatch.setattr(tl_native, "_tried", False)
    with pytest.warns(RuntimeWarning, match="native kernel is unavailable .*no C compiler"):
        assert tl_native.library() is None
    assert tl_native.library() is None  # warned once
    with pytest.raises(RuntimeError, match="no C compiler"):
        tl_native.build()
    assert tl_native.main([]) == 1
    est = SourceEstimator(8, "cpu", "realistic", path="fused")
    walls = torch.zeros((1, 8, 8), dtype=torch.bool)
    log_post = est.prior(walls)
    est.update(log_post, walls, torch.tensor([[[0, 0]]]), torch.tensor([[20.0]]))
    assert float(est.posterior(log_post).sum()) == pytest.approx(1.0, abs=1e-5)


def test_bad_input_gets_a_clear_error() -> None:
    k, n, side, levels, q = 2, 3, 4, 8, 40
    cells = side * side
    args = dict(post=torch.zeros((k, cells, levels)), log_rate=torch.zeros((q, levels)),
                factor=torch.zeros(q), strength=torch.ones(levels), background=torch.ones(levels),
                positions=torch.zeros((k, n, 2), dtype=torch.int64), rects=torch.full((k, 1, 4), -10.0),
                count=True, span=19, readings=torch.ones((k, n)),
                out=torch.zeros((k, cells), dtype=torch.bool), marginal=torch.empty((k, cells)),
                dead_cell=0.0)
    tl_native.levels_update(**args)
    with pytest.raises(ValueError, match=r"positions must be a contiguous CPU torch.int64 tensor of shape"):
        tl_native.levels_update(**{**args, "positions": torch.zeros((k, n, 2), dtype=torch.int32)})
    with pytest.raises(ValueError, match="post must be a contiguous"):
        tl_native.levels_update(**{**args, "post": torch.zeros((k, levels, cells)).transpose(1, 2)})
    with pytest.raises(ValueError, match="positions must lie on the 4x4 grid"):
        tl_native.levels_update(**{**args, "positions": torch.full((k, n, 2), 4, dtype=torch.int64)})
    wall = torch.tensor([[[0.5, -0.5, 1.5, 3.5]]]).expand(k, 1, 4).contiguous()  # row 1: crossed once
    with pytest.raises(ValueError, match="outside the estimator's tables"):  # tables for no crossing
        tl_native.levels_update(**{**args, "rects": wall, "log_rate": torch.zeros((19, levels)),
                                   "factor": torch.zeros(19)})
    grid = 6
    one = dict(post=torch.zeros((1, grid * grid)), rate=torch.ones(200), log_rate=torch.zeros(200), span=51,
               positions=torch.tensor([[[0, 0]]]), table=torch.zeros((2, 36, grid, 2, 36), dtype=torch.int8),
               segments=torch.tensor([[[-1, -1, -2, -2]]]), readings=torch.ones((1, 1)),
               out=torch.zeros((1, 36), dtype=torch.bool), posterior=None)
    tl_native.single_update(**one)
    with pytest.raises(ValueError, match="positions must lie on the 6x6 grid"):
        tl_native.single_update(**{**one, "positions": torch.tensor([[[0, 6]]])})
    with pytest.raises(ValueError, match="wall segment falls outside"):
        tl_native.single_update(**{**one, "segments": torch.tensor([[[9, 0, 9, 3]]])})


@pytest.mark.parametrize(("sensing", "grid"), [("realistic", 12), ("paper-simple", 13)])
def test_a_call_split_over_threads_is_bit_for_bit_the_one_thread_call(sensing, grid, monkeypatch) -> None:
    """Each kernel call splits its episodes into contiguous parts, one per thread: the same posteriors,
    observations and expected distances whatever the count (7 episodes: uneven parts)."""
    monkeypatch.setattr(tl_native, "MIN_PART_WORK", 1)  # split however small the call
    runs = {}
    for count in (1, 2, 3):
        with tl_native.split(count):
            assert tl_native.threads() == count
            runs[count] = estimator_trace(sensing, grid, "fused", steps=30, batch=7)
    for count in (2, 3):
        for got, want in zip(runs[count], runs[1], strict=True):
            assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
    p = runs[1][-1][1]
    est = SourceEstimator(grid, "cpu", sensing, path="fused")
    with tl_native.split(3):
        split = est.expected_from_posterior(p)
    with tl_native.split(1):
        assert torch.equal(split, est.expected_from_posterior(p))


def test_an_error_in_any_part_of_a_split_call_is_raised(monkeypatch) -> None:
    monkeypatch.setattr(tl_native, "MIN_PART_WORK", 1)
    k, n, side, levels = 4, 1, 4, 8
    cells = side * side
    rects = torch.full((k, 1, 4), -10.0)
    rects[k - 1] = torch.tensor([0.5, -0.5, 1.5, 3.5])  # the last episode's reading crosses a wall
    args = dict(post=torch.zeros((k, cells, levels)), log_rate=torch.zeros((19, levels)),
                factor=torch.zeros(19), strength=torch.ones(levels), background=torch.ones(levels),
                positions=torch.zeros((k, n, 2), dtype=torch.int64), rects=rects, count=True, span=19,
                readings=torch.ones((k, n)), out=torch.zeros((k, cells), dtype=torch.bool), marginal=None,
                dead_cell=0.0)
    for count in (1, 2):
        with tl_native.split(count), pytest.raises(ValueError, match="outside the estimator's tables"):
            tl_native.levels_update(**args)


def test_the_kernel_threads_follow_torch_unless_set_and_a_bad_count_is_refused(monkeypatch) -> None:
    monkeypatch.delenv(tl_native.THREADS_VAR, raising=False)
    assert tl_native.threads() == torch.get_num_threads()
    monkeypatch.setenv(tl_native.THREADS_VAR, "3")
    assert tl_native.threads() == 3
    with tl_native.split(1):
        assert tl_native.threads() == 1
    assert tl_native.threads() == 3
    for bad in ("0", "-1", "two", "1.5"):
        monkeypatch.setenv(tl_native.THREADS_VAR, bad)
        with pytest.raises(ValueError, match=rf"MEDC_NATIVE_THREADS must be an integer >= 1, got '{bad}'"):
            tl_native.threads()
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="kernel threads must be an integer >= 1"), tl_native.split(bad):
            pass


def test_a_call_is_split_into_contiguous_parts_only_when_each_has_enough_work() -> None:
    calls = []

    def record(pointer, episodes, other):
        calls.append((pointer, episodes, other))
        return 0

    least = tl_native.MIN_PART_WORK
    with tl_native.split(3):
        assert tl_native._spread(record, [1000, 7, "x"], {0: 10}, 1, 7, 3 * least) == [0] * 3
        assert sorted(calls) == [(1000, 2, "x"), (1020, 2, "x"), (1040, 3, "x")]
        calls.clear()
        tl_native._spread(record, [1000, 7, "x"], {0: 10}, 1, 7, 2 * least - 1)
        assert calls == [(1000, 7, "x")]  # too little work for two parts: one call


def _split_in_child(queue) -> None:
    calls = []
    with tl_native.split(2):
        tl_native._spread(lambda p, k: calls.append((p, k)), [0, 4], {0: 1}, 1, 4, 1 << 30)
    queue.put(sorted(calls))


@pytest.mark.timing
def test_a_forked_child_splits_on_its_own_pool() -> None:
    """A child forked after its parent made the helper pool has none of the pool's threads: it makes its
    own instead of waiting forever on the parent's."""
    import multiprocessing

    with tl_native.split(2):
        tl_native._spread(lambda p, k: None, [0, 4], {0: 1}, 1, 4, 1 << 30)  # the parent's pool exists
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_split_in_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=120) == [(0, 2), (2, 2)]
    finally:
        child.join(timeout=120)
    assert child.exitcode == 0
