"""Compiled per-frame kernels: numba's ``njit`` with the project's settings.

The tracker's per-frame work is many small array operations (tens of
segments, a few hundred edges, eight windows per camera), where NumPy's
per-call overhead, not the arithmetic, sets the time. The kernels that replace
those chains are plain loops compiled by numba that keep the arithmetic of the
NumPy code, operation for operation, so most results agree to the last bit.
Where they cannot (NumPy's SIMD ``arctan2`` and the BLAS/LAPACK order of small
matrix products and 2x2 solves round differently) they agree to rounding
(1e-12 px, 1e-15 in the pose); each kernel's docstring or test says which.

``cache=True`` writes the machine code next to the module (``__pycache__``):
the first process compiles (a few seconds), later ones load it. No
``fastmath`` (it would reorder sums and contract multiply-adds), and NumPy's
error model (a float division by zero gives inf or NaN, as in NumPy, instead
of raising).
"""

from __future__ import annotations

import os
from pathlib import Path

import numba

__all__ = ["njit", "KERNELS", "compiled_count", "drop_stale_caches"]

#: Helpers other files' kernels compile into themselves (:mod:`vespro.numerics`).
SHARED_HELPERS = Path(__file__).with_name("numerics.py")

KERNELS: list = []  # every kernel made here, in the order its module was imported (vespro.warmup)


def drop_stale_caches(root: Path = Path(__file__).parent, shared: Path = SHARED_HELPERS) -> int:
    """Forget every cached kernel older than ``shared``; returns how many were forgotten.

    numba checks a cached kernel against its own source file only, but a kernel
    compiles the helpers it calls into itself: after a change to the shared helpers,
    the kernels of other files would still load the old machine code. Their cache
    indexes (``__pycache__/*.nbi`` under ``root``) older than the helpers' file are
    removed, so those kernels compile again on first use (once). Nothing happens
    where the cache lives elsewhere or cannot be written.
    """
    try:
        t = shared.stat().st_mtime
    except OSError:
        return 0
    n = 0
    for idx in root.rglob("__pycache__/*.nbi"):
        try:
            if idx.stat().st_mtime < t:
                os.remove(idx)
                n += 1
        except OSError:
            pass
    return n


drop_stale_caches()


def njit(fn):
    """``numba.njit`` with ``cache=True``, strict IEEE arithmetic and NumPy's error model."""
    kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
    KERNELS.append(kernel)
    return kernel


def compiled_count() -> tuple[int, int]:
    """(compiled, loaded): kernel signatures compiled in this process (not found in the
    on-disk cache) and loaded from it."""
    compiled = sum(sum(k.stats.cache_misses.values()) for k in KERNELS)
    return compiled, sum(sum(k.stats.cache_hits.values()) for k in KERNELS)
