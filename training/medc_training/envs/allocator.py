"""Keep freed memory in the process instead of returning it to the kernel at every step.

The team estimator of a sensing model with unknown strength and background (the realistic preset)
makes a few temporaries of B × G² × levels floats per step (20 MiB at B = 256, 20×20, 48 levels).
glibc's malloc serves blocks that large from fresh ``mmap`` pages and gives them back on free, or
trims the heap's top back to the kernel, so every step pays the page faults of touching them again:
measured on the realistic 20×20 scenario of ``medc-bench env``, 1.7× the step time. PyTorch's CPU
performance guide recommends an allocator that keeps memory (jemalloc, tcmalloc) for the same
reason; :func:`keep_freed_memory` gets the effect from glibc itself with ``mallopt``: blocks up to
32 MiB from the heap, and up to 256 MiB of free heap kept. Numbers do not change, only where the
memory comes from.

Called once per process by :class:`~medc_training.envs.tl_observation.TeamMemory` when its
estimator keeps a posterior over levels. ``MEDC_MALLOC_TUNING=0`` in the environment leaves the
allocator alone; on a C library other than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
#: Largest block served from the heap (glibc's ceiling for M_MMAP_THRESHOLD on 64-bit systems).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory at the heap's top kept before it is returned to the kernel, and extra requested.
TRIM_THRESHOLD = 256 * 1024 * 1024
TOP_PAD = 64 * 1024 * 1024

_state: dict[str, bool] = {}


def keep_freed_memory() -> bool:
    """Tune glibc's malloc as the module docstring says, once per process. Returns whether the
    tuning is in effect (False when turned off, or not on glibc)."""
    if "done" in _state:
        return _state["done"]
    _state["done"] = False
    if os.environ.get("MEDC_MALLOC_TUNING", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    ok = all(mallopt(param, value) == 1 for param, value in (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD), (_M_TOP_PAD, TOP_PAD)))
    _state["done"] = ok
    return ok
