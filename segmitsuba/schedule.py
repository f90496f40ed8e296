"""What a render fixes for all of its passes, wherever they run: pass seeds and the kernel schedule.

A render is split into passes (``mi.render`` calls of the CLI, ``compare``, Dask tasks, notebooks, a user's own
loop), and a filter splits each call into pools (one segment population and one linear system each). Both are
positions in one render: pass ``i`` of a render with seed ``s`` has seed :func:`pass_seed` ``(s, i)``, and a
pool that starts after ``o`` samples per pixel of the render has the kernel size
:func:`kernel_size_at` ``(r0, alpha, o / P)`` (``P``: the render's nominal pool size). These are pure functions
of the render, so one call, many calls and tasks spread over workers use the same seeds and kernel sizes
(docs/maths.md §5).
"""

from __future__ import annotations

import math


def pass_seed(seed: int, index: int) -> int:
    """Seed of pass ``index``: pass 0 uses ``seed`` itself (a one-pass render equals ``mi.render(seed=seed)``),
    later passes a 32-bit hash of (seed, index) so that runs with nearby seeds do not share passes.

    Filters seed their pools the same way from the seed of their call, so a render split into calls of one
    pool each draws the same pools as one call."""
    if index == 0:
        return seed & 0xFFFFFFFF
    h = (seed * 0x9E3779B1 + index * 0x85EBCA77 + 0x165667B1) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    return h ^ (h >> 16)


def kernel_size_at(r0: float, alpha: float, index: float) -> float:
    """Kernel size of the pool at (possibly fractional) index ``index`` of a render.

    Progressive shrinking as in progressive photon mapping: ``r_i^2 = r0^2 prod_{j<i} (j + alpha) / (j + 1)``,
    written as ``r0^2 Gamma(i + alpha) / (Gamma(alpha) Gamma(i + 1))`` so that a pool that starts part-way
    through a nominal pool (a call of fewer samples than a pool) has a well-defined size between its
    neighbours'. ``alpha = 1`` keeps ``r0``.
    """
    if index < 0:
        raise ValueError(f"pool index must be >= 0, got {index}")
    if alpha >= 1.0 or index == 0:
        return r0
    log_ratio = math.lgamma(index + alpha) - math.lgamma(alpha) - math.lgamma(index + 1.0)
    return r0 * math.exp(0.5 * log_ratio)
