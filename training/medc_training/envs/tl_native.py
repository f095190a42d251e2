"""The source estimator's native kernel (``tl_native.c``): build, cache, load, call.

On the fused estimator path (:class:`~medc_training.envs.tl_observation.SourceEstimator`) a step's
work runs in one C pass per episode instead of about ten torch kernels over the batch: with levels,
the line of sight, the log-likelihood rows, the update, the renormalisation and the marginal over the
levels; with one level, the crossings, the rate lookups, the update and the posterior; and the
expected-distance map. The library is built with the
system C compiler (``$CC``, else ``cc``) into ``~/.cache/medc/native/tl_native-<hash>.so``
(``$MEDC_NATIVE_CACHE`` overrides the folder), keyed by the source's and the flags' hash, so an
edited kernel is rebuilt and a stale one never loaded. ``scripts/setup.sh`` builds it
(``python -m medc_training.envs.tl_native``); a process that finds none builds it on first use. With
no compiler, or ``MEDC_NATIVE=0``, the estimator takes its torch fused path (a one-line warning
says why when the kernel was wanted).

Each call with enough work (:data:`MIN_PART_WORK` per part) splits its episodes into contiguous parts
run at once on up to :func:`threads` threads (the calling one and a small pool; ctypes lets go of the
GIL during the call). Episodes are independent and each runs the same arithmetic whatever part it
falls in, so the results are bit for bit those of one thread.
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("tl_native.c")
#: x86-64-v2 (SSE4.2) runs on any x86-64 machine of the last decade, CI's included; the kernel's hot
#: loops are cloned for x86-64-v3 inside the library (target_clones), picked at load time. The kernel
#: sees no NaN or infinity (its inputs are clamped) and no signed zero matters to it: telling the
#: compiler so lets it vectorise the floors (max) and the exp, about 8x the scalar loop.
#: No fused multiply-add contraction: every product and sum rounds on its own, as torch's element-wise
#: ops do, so the one-level update is bit for bit the torch path's on any machine.
_COMMON = ("-O3", "-fopenmp-simd", "-ffinite-math-only", "-fno-signed-zeros", "-ffp-contract=off", "-fPIC",
           "-shared")
FLAGS = ("-march=x86-64-v2", *_COMMON)
PORTABLE_FLAGS = _COMMON  # a compiler for another architecture

_lib: ctypes.CDLL | None = None
_tried = False

_i64, _f32, _ptr = ctypes.c_int64, ctypes.c_float, ctypes.c_void_p


_off = 0
#: The variable that says how many threads a kernel call splits its episodes over (an integer >= 1);
#: unset: torch's intra-op thread count (``--threads`` of the training commands), so a run given one core
#: keeps to one.
THREADS_VAR = "MEDC_NATIVE_THREADS"
_threads_override: int | None = None
#: A call is split only into parts of at least this much work (about the floats each part touches): a
#: helper thread takes 0.05-1 ms to wake up (more on a loaded machine), more than a small call's work.
MIN_PART_WORK = 1 << 18
_pool: tuple[int, int, ThreadPoolExecutor] | None = None  # (the pid that made it, its threads, the pool)


def enabled() -> bool:
    """Whether the kernel may be used: ``MEDC_NATIVE`` is not ``0`` and no :func:`turned_off` block
    is running."""
    return _off == 0 and os.environ.get("MEDC_NATIVE", "1").strip() != "0"


@contextmanager
def turned_off():
    """Inside the block every estimator takes its torch path (the benchmarks time both in one run)."""
    global _off
    _off += 1
    try:
        yield
    finally:
        _off -= 1


def threads() -> int:
    """The threads a kernel call splits its episodes over: a :func:`split` block's count, else
    ``$MEDC_NATIVE_THREADS``, else torch's intra-op thread count. Raises ValueError on a bad
    ``$MEDC_NATIVE_THREADS``."""
    if _threads_override is not None:
        return _threads_override
    raw = os.environ.get(THREADS_VAR, "").strip()
    if not raw:
        return max(1, torch.get_num_threads())
    if not raw.isdigit() or int(raw) < 1:
        raise ValueError(f"{THREADS_VAR} must be an integer >= 1, got {raw!r}")
    return int(raw)


@contextmanager
def split(count: int):
    """Inside the block every kernel call splits its episodes over ``count`` threads (1: all on the
    calling thread; the benchmarks time both in one run)."""
    global _threads_override
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"kernel threads must be an integer >= 1, got {count!r}")
    before, _threads_override = _threads_override, count
    try:
        yield
    finally:
        _threads_override = before


def _executor(workers: int) -> ThreadPoolExecutor:
    """The pool of helper threads (made again in a forked child, which has none of its parent's)."""
    global _pool
    if _pool is None or _pool[0] != os.getpid() or _pool[1] < workers:
        if _pool is not None and _pool[0] == os.getpid():
            _pool[2].shutdown(wait=False)  # idle: every call waits for its parts
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="medc-native")
        _pool = (os.getpid(), workers, pool)
    return _pool[2]


def _spread(fn, args: list, per_episode: dict[int, int], count_at: int, k: int, work: int) -> list:
    """``fn(*args)`` over k episodes in up to :func:`threads` contiguous parts at once (none under
    :data:`MIN_PART_WORK` of the call's ``work``), the first on this thread; returns each part's
    result. ``args[i]`` for i in ``per_episode`` is a pointer (or None) that advances
    ``per_episode[i]`` bytes per episode; ``args[count_at]`` is the part's episodes."""
    parts = min(threads(), k, work // MIN_PART_WORK)
    if parts <= 1:
        return [fn(*args)]
    bounds = [k * i // parts for i in range(parts + 1)]

    def part(i: int):
        lo, hi = bounds[i], bounds[i + 1]
        mine = list(args)
        for at, step in per_episode.items():
            mine[at] = None if args[at] is None else args[at] + lo * step
        mine[count_at] = hi - lo
        return fn(*mine)

    futures = [_executor(parts - 1).submit(part, i) for i in range(1, parts)]
    try:
        first = part(0)
    finally:  # the helpers write into the caller's tensors: never return before they are done
        rest = [f.result() for f in futures]
    return [first, *rest]


def status() -> str:
    """One line for the benchmarks: whether the kernel is in use, and where from or why not."""
    if not enabled():
        return "torch path (MEDC_NATIVE=0)"
    if library() is None:
        return "torch path (no kernel: see the warning)"
    return "native kernel (tl_native.c)"


def _flags() -> tuple[str, ...]:
    return FLAGS if platform.machine() in {"x86_64", "AMD64"} else PORTABLE_FLAGS


def _compiler() -> str | None:
    return shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc") or shutil.which("clang")


def library_path() -> Path:
    """Where the library built from the current source and flags lives."""
    digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(_flags()).encode()).hexdigest()[:16]
    cache = Path(os.environ.get("MEDC_NATIVE_CACHE") or Path.home() / ".cache" / "medc" / "native")
    return cache / f"tl_native-{digest}.so"


def build(force: bool = False) -> Path:
    """Compile the kernel into the cache (unless it is there) and return its path; raises
    RuntimeError saying why when it cannot. The file appears whole or not at all (built under a
    temporary name, then renamed), so concurrent processes may build at once."""
    target = library_path()
    if target.exists() and not force:
        return target
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC, or install cc)")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run([cc, *_flags(), "-o", tmp, str(SOURCE)], capture_output=True, text=True,
                              timeout=300)
        if done.returncode != 0:
            raise RuntimeError(f"{cc} failed: {(done.stderr or done.stdout).strip()[-2000:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    lib.medc_levels_update.restype = ctypes.c_int
    lib.medc_levels_update.argtypes = [_ptr, _ptr, _ptr, _ptr, _ptr, _i64, _ptr, _ptr, _i64, ctypes.c_int,
                                       _i64, _i64, _ptr, _ptr, _ptr, _i64, _i64, _i64, _f32]
    lib.medc_levels_marginal.restype = None
    lib.medc_levels_marginal.argtypes = [_ptr, _i64, _i64, _i64, _ptr, _f32]
    lib.medc_single_update.restype = ctypes.c_int
    lib.medc_single_update.argtypes = [_ptr, _ptr, _ptr, _i64, _i64, _ptr, _ptr, _ptr, _i64, _ptr, _ptr, _ptr,
                                       _i64, _i64, _i64]
    lib.medc_single_posterior.restype = None
    lib.medc_single_posterior.argtypes = [_ptr, _i64, _i64, _ptr]
    lib.medc_expected_moves.restype = None
    lib.medc_expected_moves.argtypes = [_ptr, _i64, _i64, _ptr]
    lib.medc_factor_moments.restype = ctypes.c_int
    lib.medc_factor_moments.argtypes = [_ptr, _ptr, _i64, _ptr, _ptr, _i64, ctypes.c_int, _i64, _i64, _ptr,
                                        _ptr, _i64, _i64]
    return lib


def library() -> ctypes.CDLL | None:
    """The loaded kernel, or None (``MEDC_NATIVE=0``, or it could not be built or loaded: warned
    once). Builds it on first use when the cache has none."""
    global _lib, _tried
    if not enabled():
        return None
    if not _tried:
        _tried = True
        try:
            _lib = _bind(ctypes.CDLL(str(build())))
        except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
            warnings.warn(f"medc: the estimator's native kernel is unavailable ({str(exc).splitlines()[0]}); "
                          "using the torch path", RuntimeWarning, stacklevel=2)
            _lib = None
    return _lib


def _library_or_raise() -> ctypes.CDLL:
    lib = library()
    if lib is None:
        raise RuntimeError("the estimator's native kernel is unavailable")
    return lib


def usable(*tensors: torch.Tensor) -> bool:
    """Whether the kernel can take ``tensors``: it is loaded and they are contiguous CPU tensors."""
    return (library() is not None
            and all(t.device.type == "cpu" and t.is_contiguous() for t in tensors))


def _check(t: torch.Tensor, dtype: torch.dtype, shape: tuple[int, ...], name: str) -> int:
    if t.dtype != dtype or tuple(t.shape) != shape or not t.is_contiguous() or t.device.type != "cpu":
        raise ValueError(f"{name} must be a contiguous CPU {dtype} tensor of shape {shape}, got "
                         f"{t.dtype} {tuple(t.shape)} on {t.device}")
    return t.data_ptr()


def _episode_bytes(at: dict[int, torch.Tensor | None]) -> dict[int, int]:
    """{argument index: the bytes one episode takes} of the per-episode tensors passed at those
    indices (contiguous, episodes first; None: no tensor), for :func:`_spread`."""
    return {i: 0 if t is None else t.stride(0) * t.element_size() for i, t in at.items()}


def _check_on_grid(positions: torch.Tensor, g: int) -> None:
    """The kernel indexes its tables by position: one off the grid would read outside them."""
    if bool(((positions < 0) | (positions >= g)).any()):
        raise ValueError(f"positions must lie on the {g}x{g} grid")


def levels_update(post: torch.Tensor, log_rate: torch.Tensor, factor: torch.Tensor, strength: torch.Tensor,
                  background: torch.Tensor, positions: torch.Tensor, rects: torch.Tensor, count: bool,
                  span: int, readings: torch.Tensor, out: torch.Tensor, marginal: torch.Tensor | None,
                  dead_cell: float) -> None:
    """One step of the estimator over a cells-major posterior over levels, in place (``tl_native.c``),
    the line of sight included (the exact rule, :func:`~medc_training.envs.tl_sensing.sight_lines`).

    post float32 [K, G², L]; log_rate float32 [Q, L] and factor float32 [Q] per (d², walls crossed)
    pair q = d² + span * crossed; strength, background float32 [L]; positions int64 [K, N, 2] on the
    G×G grid; rects float32 [K, Z, 4] (:func:`~medc_training.envs.tl_sensing.wall_rectangles`);
    ``count``: walls crossed are counted (else whether any is); readings float32 [K, N]; out bool
    [K, G²] (cells ruled out); marginal float32 [K, G²] or None (written: the normalised marginal
    posterior, cells whose sum is at most ``dead_cell`` exactly 0).
    """
    lib = _library_or_raise()
    k, cells, levels = post.shape
    g = math.isqrt(cells)
    n, z, q = positions.shape[1], rects.shape[1], log_rate.shape[0]
    args = [
        _check(post, torch.float32, (k, g * g, levels), "post"),
        _check(log_rate, torch.float32, (q, levels), "log_rate"),
        _check(factor, torch.float32, (q,), "factor"),
        _check(strength, torch.float32, (levels,), "strength"),
        _check(background, torch.float32, (levels,), "background"),
        q,
        _check(positions, torch.int64, (k, n, 2), "positions"),
        _check(rects, torch.float32, (k, z, 4), "rects"),
        z, int(bool(count)), g, int(span),
        _check(readings, torch.float32, (k, n), "readings"),
        _check(out, torch.bool, (k, cells), "out"),
        None if marginal is None else _check(marginal, torch.float32, (k, cells), "marginal"),
        k, n, levels, float(dead_cell),
    ]
    _check_on_grid(positions, g)
    per_episode = _episode_bytes({0: post, 6: positions, 7: rects, 12: readings, 13: out, 14: marginal})
    if any(_spread(lib.medc_levels_update, args, per_episode, 15, k, k * cells * (levels + n))):
        raise ValueError("a (d², walls crossed) pair falls outside the estimator's tables")


def levels_marginal(post: torch.Tensor, marginal: torch.Tensor, dead_cell: float) -> None:
    """The normalised marginal posterior float32 [K, C] of cells-major ``post`` float32 [K, C, L]
    into ``marginal`` (the update's step 3 alone)."""
    lib = _library_or_raise()
    k, cells, levels = post.shape
    args = [_check(post, torch.float32, (k, cells, levels), "post"), k, cells, levels,
            _check(marginal, torch.float32, (k, cells), "marginal"), float(dead_cell)]
    _spread(lib.medc_levels_marginal, args, _episode_bytes({0: post, 4: marginal}), 1, k, k * cells * levels)


def single_update(post: torch.Tensor, rate: torch.Tensor, log_rate: torch.Tensor, span: int,
                  positions: torch.Tensor, table: torch.Tensor, segments: torch.Tensor,
                  readings: torch.Tensor, out: torch.Tensor, posterior: torch.Tensor | None) -> None:
    """One step of the one-level estimator (the sampled line rule, maps made of wall segments), in
    place (``tl_native.c``): walls crossed from the crossing ``table`` (int8 [2, G², G, 2, G²],
    :func:`~medc_training.envs.tl_sensing.segment_crossings`) and ``segments`` (int64 [K, Z, 4]),
    rate and log rate float32 [Q] per q = crossed * span + d², readings float32 [K, N] at
    ``positions`` int64 [K, N, 2]; post float32 [K, G²]; out bool [K, G²] (cells ruled out);
    ``posterior`` float32 [K, G²] or None (written: the normalised posterior)."""
    lib = _library_or_raise()
    k, cells = post.shape
    g = table.shape[2] if table.dim() == 5 else -1
    n, z, q = positions.shape[1], segments.shape[1], rate.shape[0]
    args = [
        _check(post, torch.float32, (k, g * g), "post"),
        _check(rate, torch.float32, (q,), "rate"),
        _check(log_rate, torch.float32, (q,), "log_rate"),
        q, int(span),
        _check(positions, torch.int64, (k, n, 2), "positions"),
        _check(table, torch.int8, (2, cells, g, 2, cells), "table"),
        _check(segments, torch.int64, (k, z, 4), "segments"),
        z,
        _check(readings, torch.float32, (k, n), "readings"),
        _check(out, torch.bool, (k, cells), "out"),
        None if posterior is None else _check(posterior, torch.float32, (k, cells), "posterior"),
        k, n, g,
    ]
    _check_on_grid(positions, g)
    per_episode = _episode_bytes({0: post, 5: positions, 7: segments, 9: readings, 10: out, 11: posterior})
    if any(_spread(lib.medc_single_update, args, per_episode, 12, k, k * cells * n * (z + 1))):
        raise ValueError("a (walls crossed, d²) pair or a wall segment falls outside the estimator's tables")


def single_posterior(post: torch.Tensor) -> torch.Tensor:
    """float32 [K, C]: the posterior of one-level log posteriors ``post`` float32 [K, C] (exp, cells
    at or below EXP_FLOOR exactly 0, normalised), as :func:`single_update` writes it."""
    lib = _library_or_raise()
    k, cells = post.shape
    p = torch.empty((k, cells), device=post.device)
    args = [_check(post, torch.float32, (k, cells), "post"), k, cells, p.data_ptr()]
    _spread(lib.medc_single_posterior, args, _episode_bytes({0: post, 3: p}), 1, k, k * cells)
    return p


def expected_moves(posterior: torch.Tensor, grid: int) -> torch.Tensor:
    """float32 [K, G²]: the posterior-expected Chebyshev distance from each cell to the source, of
    posteriors float32 [K, G²] (``SourceEstimator.expected_from_posterior``)."""
    lib = _library_or_raise()
    k = posterior.shape[0]
    expected = torch.empty((k, grid * grid), device=posterior.device)
    args = [_check(posterior, torch.float32, (k, grid * grid), "posterior"), k, grid, expected.data_ptr()]
    _spread(lib.medc_expected_moves, args, _episode_bytes({0: posterior, 3: expected}), 1, k, k * grid * grid)
    return expected


def factor_moments(posterior: torch.Tensor, factor: torch.Tensor, cand: torch.Tensor, rects: torch.Tensor,
                   count: bool, span: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(m1, m2) float32 [K, M]: the first two moments over the posterior float32 [K, G²] of the
    geometric factor between each candidate sensor cell ``cand`` int64 [K, M, 2] and every source
    cell, the factor looked up in ``factor`` float32 [Q] by the pair q = d² + span * walls crossed
    (the exact line rule through ``rects`` float32 [K, Z, 4]; ``count``: walls crossed are counted,
    else whether any is), for ``TeamMemory.information_map``."""
    lib = _library_or_raise()
    k, cells = posterior.shape
    g = math.isqrt(cells)
    m, z, q = cand.shape[1], rects.shape[1], factor.shape[0]
    m1 = torch.empty((k, m), device=posterior.device)
    m2 = torch.empty((k, m), device=posterior.device)
    args = [
        _check(posterior, torch.float32, (k, g * g), "posterior"),
        _check(factor, torch.float32, (q,), "factor"),
        q,
        _check(cand, torch.int64, (k, m, 2), "cand"),
        _check(rects, torch.float32, (k, z, 4), "rects"),
        z, int(bool(count)), g, int(span), m1.data_ptr(), m2.data_ptr(), k, m,
    ]
    _check_on_grid(cand, g)
    per_episode = _episode_bytes({0: posterior, 3: cand, 4: rects, 9: m1, 10: m2})
    if any(_spread(lib.medc_factor_moments, args, per_episode, 11, k, k * m * cells * (z + 1))):
        raise ValueError("a (d², walls crossed) pair falls outside the estimator's tables")
    return m1, m2


def main(argv: list[str] | None = None) -> int:
    """Build the kernel into the cache (``scripts/setup.sh``) and print its path."""
    p = argparse.ArgumentParser(prog="python -m medc_training.envs.tl_native", description=main.__doc__)
    p.add_argument("--force", action="store_true", help="rebuild even when the cache has it")
    args = p.parse_args(argv)
    try:
        path = build(force=args.force)
        _bind(ctypes.CDLL(str(path)))
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        print(f"tl_native: not built: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
