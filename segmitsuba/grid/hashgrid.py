"""Hash grids held entirely in Dr.Jit arrays: fixed-radius neighbour search and jittered voxel clusters.

Two structures share the same ingredients (docs/maths.md §5):

* :class:`RadiusGrid` -- all stored points within ``r`` of each query point.
* :class:`ClusterGrid` -- voxels of side ``h`` whose origin is jittered every pass, split by a coarse normal
  bin; every (voxel, normal bin) is one kernel domain ("cluster"), with its kernel area ``A(C)`` from
  :func:`plane_cube_area`.

Both are built with counting sorts (histogram -> exclusive prefix sum -> stable ordering) and queried with
symbolic ``dr.while_loop`` kernels, so no Python loop ever runs over points and nothing goes through NumPy.
Every scalar that changes from pass to pass (grid origin / jitter, cell size, radius, table mask and size,
key dimensions, radix shifts) enters the kernels through ``dr.opaque`` values, so a new pass with new values
reuses the compiled kernels. Only *structural* parameters (``subdiv``, ``normal_bins``, the user's body
function, the array types) select different kernels.

Invalid input policy: a non-finite position among the *active* stored points, or ``r``/``h`` that is not a
finite positive number, raises :class:`ValueError` at build time (one host sync that also reads the bounding
box). Points are excluded by passing ``active=False`` for them; excluded points are never returned by any
query and get cluster id :data:`INVALID`. Non-finite *query* points are masked out (they find no
neighbours and lie in no cluster) because checking them would cost a sync per query.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import importlib
import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import drjit as dr

#: Cluster id / index value meaning "none".
INVALID = 0xFFFFFFFF

#: Largest |cell coordinate| allowed: beyond 2^24 a float32 cell coordinate is no longer exact (and the
#: positions themselves are coarser than the cells), so the grid would silently merge cells.
_MAX_CELL = float(1 << 24)

#: Widest radix digit of the counting-sort passes on the CPU (LLVM) and on CUDA. Dr.Jit's own radix sort uses 11
#: bits; on the CPU one pass of up to 16 bits is faster than two of 11 (1.1M keys of 15 bits: 6.3-6.9 -> 4.3 ms,
#: 4M of 16 bits: 42-47 -> 30-32 ms, 2 threads) and not slower for wider keys; on CUDA the buckets must fit in
#: shared memory (not measured there).
_RADIX_BITS = {"llvm": 16, "cuda": 11}

#: Entries per lane of :func:`reduce_runs` (16-128 measured within 15% of each other on cluster sums of ~400
#: entries)
RUN_PIECE = 64

__all__ = [
    "INVALID",
    "RadiusGrid",
    "ClusterGrid",
    "plane_cube_area",
    "normal_bin",
    "random_offset",
    "counting_sort",
    "reduce_runs",
    "run_pieces",
]


# --------------------------------------------------------------------------------------------------------
# helpers


def _namespace(tp: type) -> Any:
    """The ``drjit.<backend>[.ad]`` module matching an array type (also for ``mi.Point3f`` and friends)."""
    backend = dr.backend_v(tp)
    names = {dr.JitBackend.LLVM: "llvm", dr.JitBackend.CUDA: "cuda"}
    if backend not in names:
        raise TypeError(f"hash grid: need a JIT (LLVM/CUDA) array type, got {tp!r}")
    return importlib.import_module(f"drjit.{names[backend]}" + (".ad" if dr.is_diff_v(tp) else ""))


def _positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"hash grid: {name} must be a finite number > 0, got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"hash grid: {name} must be a finite number > 0, got {value!r}")
    return v


def _pow2_table(name: str, size: int | None, n: int) -> int:
    """Hash table size: ``size`` if given (must be a power of two), else the next power of two >= n."""
    if size is None:
        return 1 << max(0, (max(n, 1) - 1).bit_length())
    size = int(size)
    if size < 1 or size & (size - 1):
        raise ValueError(f"hash grid: {name} must be a power of two >= 1, got {size}")
    return size


def _as_points(m: Any, points: Any, n: int | None = None) -> Any:
    p = m.Array3f(dr.detach(points))
    if n is not None and dr.width(p) != n:
        raise ValueError(f"hash grid: expected {n} entries, got {dr.width(p)}")
    return p


def _mask(m: Any, active: Any, n: int) -> Any:
    if active is None:
        return dr.full(m.Bool, True, n)
    a = m.Bool(active)
    if dr.width(a) == 1 and n != 1:
        a = dr.full(m.Bool, bool(a[0]), n)
    if dr.width(a) != n:
        raise ValueError(f"hash grid: active mask has {dr.width(a)} entries for {n} points")
    return a


def _isfinite3(p: Any) -> Any:
    return dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z)


def _u32(m: Any, x: Any) -> Any:
    """Bit pattern of an Int32 as UInt32 (two's complement), for hashing."""
    return dr.reinterpret_array(m.UInt32, x)


def _mix32(h: Any) -> Any:
    """A cheap avalanche (lowbias32 finaliser) so that neighbouring cells scatter over the table."""
    h = h ^ (h >> 16)
    h = h * 0x7FEB352D
    h = h ^ (h >> 15)
    h = h * 0x846CA68B
    return h ^ (h >> 16)


def _row_hash(m: Any, cy: Any, cz: Any) -> Any:
    """Hash of an x-row of cells. A cell's slot is ``row_hash(y, z) + x``, so the cells of one x-row occupy
    consecutive slots and a query reads each row of its neighbourhood as one contiguous range."""
    return _mix32(_u32(m, cy) * 0x9E3779B1 ^ _u32(m, cz) * 0x85EBCA77)


def _cell_hash(m: Any, c: Any, b: Any) -> Any:
    """Hash of a (voxel, normal bin) key, for the cluster table."""
    return _mix32(_u32(m, c.x) * 0x9E3779B1 ^ _u32(m, c.y) * 0x85EBCA77 ^ _u32(m, c.z) * 0xC2B2AE3D ^ b)


def _bounds_and_checks(m: Any, p: Any, active: Any, origin: Any, inv: Any) -> tuple[int, list[float], list[float], int]:
    """One host sync: number of active points, number of non-finite active points, and the range of the
    float cell coordinates ``floor((p - origin) * inv)`` over the active finite points."""
    fin = _isfinite3(p)
    ok = active & fin
    fc = dr.floor((p - origin) * inv)
    # once, not in each reduction's own kernel (the points are often lazy gathers)
    dr.eval(fin, ok, fc)
    big = m.Float(dr.inf)
    red = [
        dr.sum(m.UInt32(active)),
        dr.sum(m.UInt32(active & ~fin)),
        dr.min(dr.select(ok, fc.x, big)),
        dr.min(dr.select(ok, fc.y, big)),
        dr.min(dr.select(ok, fc.z, big)),
        dr.max(dr.select(ok, fc.x, -big)),
        dr.max(dr.select(ok, fc.y, -big)),
        dr.max(dr.select(ok, fc.z, -big)),
    ]
    dr.eval(red)
    vals = [r[0] for r in red]
    return int(vals[0]), [float(v) for v in vals[2:5]], [float(v) for v in vals[5:8]], int(vals[1])


def _check_cells(what: str, lo: list[float], hi: list[float]) -> None:
    if max(max(abs(v) for v in lo), max(abs(v) for v in hi)) > _MAX_CELL:
        raise ValueError(
            f"hash grid: {what} is too small for these coordinates: cell coordinates reach "
            f"{max(max(map(abs, lo)), max(map(abs, hi))):.3g} > 2^24, where float32 positions can no longer "
            "tell the cells apart. Use a larger cell size or recentre the points."
        )


def counting_sort(keys: Any, bits: int, with_keys: bool = False) -> Any:
    """Stable permutation sorting ``keys`` (UInt32 or UInt64, each below ``2^bits``); with
    ``with_keys``, ``(permutation, sorted keys)`` (the sort permutes them anyway; gathering them again through
    the permutation would read them at random).

    An LSD radix sort of ``ceil(bits / R)`` passes of equal digits (``R``: :data:`_RADIX_BITS`); each pass is a
    counting sort (per-block histogram -> exclusive prefix sum -> stable scatter, Dr.Jit's ``block_mkperm``).
    Only as many passes as the keys need are run (fewer than ``dr.argsort``'s fixed 3 or 6), and the digit
    shift and mask are opaque, so the number of passes can change from pass to pass without compiling new
    kernels. Stability makes builds reproducible: equal keys keep their input order.
    """
    m = _namespace(type(keys))
    n = dr.width(keys)
    if n <= 1 or bits <= 0:
        return (dr.arange(m.UInt32, n), type(keys)(keys)) if with_keys else dr.arange(m.UInt32, n)
    if not hasattr(dr.detail, "block_mkperm"):  # pragma: no cover - other Dr.Jit versions
        perm = dr.argsort(keys)
        return (perm, dr.gather(type(keys), keys, perm)) if with_keys else perm
    tp = type(keys)
    ordinal = tp(keys)
    perm = dr.arange(m.UInt32, n)
    dr.eval(ordinal, perm)
    radix = _RADIX_BITS["llvm" if dr.backend_v(tp) == dr.JitBackend.LLVM else "cuda"]
    passes = -(-bits // radix)
    width = -(-bits // passes)  # digits as even as the passes allow
    mask = dr.opaque(tp, (1 << width) - 1)
    for k in range(passes):
        # Every pass runs the same two kernels (digit; permute keys + permutation), evaluated separately so
        # that Dr.Jit does not fuse them differently for the first/last pass, and the shift and digit mask are
        # opaque: a change in the number of passes or in the digit's width (table size, key range) then
        # compiles nothing new.
        digit = m.UInt32((ordinal >> dr.opaque(tp, k * width)) & mask)
        dr.eval(digit)
        step = dr.detail.block_mkperm(digit, n, 1 << width)
        ordinal, perm = dr.gather(tp, ordinal, step), dr.gather(m.UInt32, perm, step)
        dr.eval(ordinal, perm)
    return (perm, ordinal) if with_keys else perm


def run_pieces(offsets: Any, end: Any = None, piece: int = RUN_PIECE) -> tuple[Any, Any, Any]:
    """Lanes that cover the runs ``offsets[k] .. offsets[k + 1] - 1`` of a CSR list (``offsets``: UInt32[K + 1]), or
    with ``end`` the runs ``offsets[k] .. end[k] - 1`` (which may overlap), in pieces of at most ``piece``
    entries: ``(run, start, stop)`` per lane, consecutive lanes in run order. For :func:`reduce_runs`; build them
    once for lists that are reduced many times."""
    m = _namespace(type(offsets))
    runs = dr.width(offsets) - 1 if end is None else dr.width(offsets)
    if runs <= 0:
        return dr.zeros(m.UInt32, 0), dr.zeros(m.UInt32, 0), dr.zeros(m.UInt32, 0)
    k = dr.arange(m.UInt32, runs)
    begin = dr.gather(m.UInt32, offsets, k)
    end = dr.gather(m.UInt32, offsets, k + 1) if end is None else m.UInt32(end)
    size = dr.opaque(m.UInt32, piece)
    counts = (end - begin + size - 1) // size
    lane_offsets, total = _csr_from_counts(m, counts)
    if total == 0:
        return dr.zeros(m.UInt32, 0), dr.zeros(m.UInt32, 0), dr.zeros(m.UInt32, 0)
    nonempty = dr.compress(counts > 0)
    first = dr.zeros(m.UInt32, total)
    dr.scatter(first, m.UInt32(1), dr.gather(m.UInt32, lane_offsets, nonempty))
    run = dr.gather(m.UInt32, nonempty, dr.cumsum(first) - 1)
    start = (dr.gather(m.UInt32, begin, run)
             + (dr.arange(m.UInt32, total) - dr.gather(m.UInt32, lane_offsets, run)) * size)
    stop = dr.minimum(start + size, dr.gather(m.UInt32, end, run))
    dr.eval(run, start, stop)
    return run, start, stop


def reduce_runs(value_of: Callable[[Any], tuple], types: Sequence[type], pieces: tuple[Any, Any, Any], size: int,
                ops: Sequence[Any] | None = None) -> list:
    """``out[k][r] = op_k`` over ``value_of(i)[k]`` of the entries ``i`` of every run ``r`` (``pieces`` from
    :func:`run_pieces`; ``op_k`` is ``ops[k]``: ``dr.ReduceOp.Add`` (default), ``Min`` or ``Max``). ``value_of``
    reads entry ``i`` (a UInt32 index), ``types`` are the types of what it returns; ``out[k]`` has ``size`` entries,
    the identity of ``op_k`` for runs without entries.

    Each lane reduces its piece in registers and the lanes of a run combine with one scatter-reduction each. On
    AVX2 CPUs that is 2-3x faster than one scatter-reduction per entry, even of sorted keys, and than a loop per
    run, which also leaves a single thread busy where runs are few."""
    ops = list(ops) if ops is not None else [dr.ReduceOp.Add] * len(types)
    identity = [{dr.ReduceOp.Add: 0, dr.ReduceOp.Min: dr.inf, dr.ReduceOp.Max: -dr.inf}[op] for op in ops]
    combine = {dr.ReduceOp.Add: lambda a, b: a + b, dr.ReduceOp.Min: dr.minimum, dr.ReduceOp.Max: dr.maximum}
    run, start, stop = pieces
    lanes = dr.width(run)
    out = [dr.full(tp, e, size) for tp, e in zip(types, identity, strict=True)]
    if lanes == 0 or size == 0:
        return out

    def body(i, acc):
        return i + 1, tuple(combine[op](a, v) for a, v, op in zip(acc, value_of(i), ops, strict=True))

    _, acc = dr.while_loop(
        state=(start, tuple(dr.full(tp, e, lanes) for tp, e in zip(types, identity, strict=True))),
        cond=lambda i, acc: i < stop,
        body=body,
        label="reduce_runs",
    )
    for target, value, op in zip(out, acc, ops, strict=True):
        # Local: the lanes of a run are consecutive (Auto would bake the size of small targets into the kernel)
        dr.scatter_reduce(op, target, value, run, mode=dr.ReduceMode.Local)
    return out


@functools.cache
def llvm_vector_width() -> int:
    """The width of Dr.Jit's LLVM vectors on this CPU (16 with AVX-512, 8 with AVX2), read from its core library;
    0 where it cannot be read."""
    try:
        for path in glob.glob(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.*")):
            lib = ctypes.CDLL(path)
            for name in ("jit_llvm_vector_width", "_Z21jit_llvm_vector_widthv"):  # C, or C++ linkage
                fn = getattr(lib, name, None)
                if fn is not None:
                    fn.restype = ctypes.c_uint32
                    return int(fn())
    except OSError:
        pass
    return 0


def scatter_sorted_runs(tp: type) -> bool:
    """Whether sums over runs of entries sorted by their run are faster as one scatter-reduction
    (``ReduceMode.Local``, which adds the lanes of a SIMD packet with the same target before one atomic each)
    than as :func:`reduce_runs`. With 16-wide vectors (AVX-512) it took half the time of :func:`reduce_runs`
    on the solve's cluster sums; with 8-wide ones (AVX2) 5% longer. On CUDA, where a lane looping over its own
    piece leaves its warp waiting, the scatter (not measured)."""
    if dr.backend_v(tp) != dr.JitBackend.LLVM:
        return True
    return llvm_vector_width() >= 16


def _histogram_offsets(m: Any, bucket: Any, n_buckets: int) -> Any:
    """Exclusive prefix sum of the histogram of ``bucket`` (values in ``[0, n_buckets]``; ``n_buckets`` is
    the sentinel of excluded entries): entry ``s`` is the start of bucket ``s`` in sorted order and entry
    ``n_buckets`` the number of non-sentinel entries."""
    counts = dr.zeros(m.UInt32, n_buckets + 1)
    # Local: pre-reduce equal slots within a SIMD packet (points sorted by cell hit one slot in a row);
    # Auto would pick Expand for small tables and bake the table size into the kernel
    dr.scatter_reduce(dr.ReduceOp.Add, counts, m.UInt32(1), bucket, mode=dr.ReduceMode.Local)
    return dr.prefix_sum(counts)


def _csr_from_counts(m: Any, counts: Any) -> tuple[Any, int]:
    """CSR offsets (``len(counts) + 1`` entries) from per-row counts, and the total (one host sync)."""
    q = dr.width(counts)
    padded = dr.zeros(m.UInt32, q + 1)
    dr.scatter(padded, counts, dr.arange(m.UInt32, q))
    offsets = dr.prefix_sum(padded)
    dr.eval(offsets)
    total = int(offsets[q])
    return offsets, total


def normal_bin(normals: Any, bins: int = 6) -> Any:
    """Coarse normal bin: ``bins=6`` gives ``2 * dominant_axis + (component < 0)``; ``bins=1`` disables
    binning. ``n`` and ``-n`` always land in different bins with 6 bins (same dominant axis -- ties go to
    the lower axis on ``|n|``, which is the same for both -- opposite sign), so the two sides of a thin wall
    never share a cluster. Zero or non-finite normals land in one fixed bin (deterministic)."""
    m = _namespace(type(normals))
    n = m.Array3f(dr.detach(normals))
    if bins == 1:
        return dr.zeros(m.UInt32, dr.width(n))
    if bins != 6:
        raise ValueError(f"normal_bin: bins must be 1 or 6, got {bins}")
    a = dr.abs(n)
    axis = dr.select((a.x >= a.y) & (a.x >= a.z), 0, dr.select(a.y >= a.z, 1, 2))
    comp = dr.select(axis == 0, n.x, dr.select(axis == 1, n.y, n.z))
    return m.UInt32(2 * axis + dr.select(comp < 0, 1, 0))


def random_offset(h: float, seed: int) -> tuple[float, float, float]:
    """A per-pass grid jitter in ``[0, h)^3`` from an integer seed (host side: three numbers per pass)."""
    h = _positive("h", h)
    out = []
    for i in range(3):
        x = (int(seed) * 3 + i + 1) * 0x9E3779B97F4A7C15 & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 33
        x = x * 0xFF51AFD7ED558CCD & 0xFFFFFFFFFFFFFFFF
        x ^= x >> 33
        out.append(min((x >> 11) / float(1 << 53) * h, math.nextafter(h, 0.0)))
    return (out[0], out[1], out[2])


# --------------------------------------------------------------------------------------------------------
# plane ∩ cube area


#: A(C) with surface points: a voxel side farther than this many mean spacings from the nearest point is taken
#: as where the surface ends (for uniform points the chance that it does not is about e^-6)
EDGE_GAPS = 6.0
#: ... in clusters of at least this many surface points (fewer cannot tell an edge from noise)
EXTENT_MIN_POINTS = 10


def plane_cube_area(point_on_plane: Any, normal: Any, cube_min: Any, h: Any) -> Any:
    """Exact area of the polygon where the plane through ``point_on_plane`` with ``normal`` cuts the
    axis-aligned cube ``[cube_min, cube_min + h]^3`` (vectorised; ``h`` a number or a Float array); ``h^2``
    where there is no such polygon (see :func:`plane_box_area`)."""
    m = _namespace(type(point_on_plane))
    h = m.Float(h)
    area = plane_box_area(point_on_plane, normal, cube_min, m.Array3f(h, h, h))
    return dr.select(area > 0, area, h * h)


def plane_box_area(point_on_plane: Any, normal: Any, box_min: Any, size: Any) -> Any:
    """Exact area of the polygon where the plane through ``point_on_plane`` with ``normal`` cuts the
    axis-aligned box ``[box_min, box_min + size]`` (vectorised); 0 where the normal is zero/non-finite or the
    plane misses the box.

    Why this formula: the polygon's edges are exactly the plane's cuts through the six cube faces, and a
    cut through the face with outward normal ``m`` runs along ``n x m`` when the polygon is walked
    counter-clockwise about ``n``. So ``area = 1/2 sum_faces (a_f x b_f) . n`` needs no vertex sorting --
    six independent Liang-Barsky line clips, branch-free. Coordinates are taken relative to the box centre
    for precision.
    """
    m = _namespace(type(point_on_plane))
    p = m.Array3f(dr.detach(point_on_plane))
    n = m.Array3f(dr.detach(normal))
    bmin = m.Array3f(dr.detach(box_min))
    halves = 0.5 * m.Array3f(dr.detach(size))
    ln = dr.norm(n)
    good = (ln > 0) & dr.isfinite(ln)
    n = dr.select(good, n / ln, m.Array3f(0, 0, 1))
    d = dr.dot(n, p - (bmin + halves))  # plane: n . x = d (x relative to the box centre)
    inf = m.Float(dr.inf)
    twice = m.Float(0)
    for k in range(3):
        u, v = (k + 1) % 3, (k + 2) % 3
        nk, nu, nv = n[k], n[u], n[v]
        s2 = nu * nu + nv * nv
        for sgn in (1.0, -1.0):
            w = sgn * halves[k]  # face coordinate along axis k
            # line in the face: nu*x_u + nv*x_v = rhs; closest point to the face centre, and direction n x m
            rhs = d - nk * w
            par = s2 > 1e-12
            scale = dr.select(par, rhs / s2, 0)
            qu, qv = scale * nu, scale * nv
            # n x (sgn e_k): components along u and v
            du, dv = -sgn * nv, sgn * nu
            t0, t1 = -inf, inf
            ok = m.Bool(par)
            for q, dd, a, nb in ((qu, du, u, nv), (qv, dv, v, nu)):
                half = halves[a]
                moving = dr.abs(dd) > 1e-12
                ta = (-half - q) / dd
                tb = (half - q) / dd
                t0 = dr.select(moving, dr.maximum(t0, dr.minimum(ta, tb)), t0)
                t1 = dr.select(moving, dr.minimum(t1, dr.maximum(ta, tb)), t1)
                # a cut parallel to axis `a` lying on a cube edge (within rounding) is shared with face `a`:
                # count it once -- here if k < a, or if face `a` is parallel to the plane (skipped there)
                aq = dr.abs(q)
                on_edge = aq >= half * (1 - 1e-5)
                owner = (k < a) | (nk * nk + nb * nb <= 1e-12)
                ok &= moving | (aq <= half * (1 + 1e-5)) & (~on_edge | owner)
            ok &= t1 > t0
            t0 = dr.select(ok, t0, 0)
            t1 = dr.select(ok, t1, 0)
            au, av = qu + t0 * du, qv + t0 * dv
            bu, bv = qu + t1 * du, qv + t1 * dv
            # (a x b) . n with a = (w, au, av), b = (w, bu, bv) in (k, u, v) order (a right-handed frame)
            cross_k = au * bv - av * bu
            cross_u = av * w - w * bv
            cross_v = w * bu - au * w
            twice += dr.select(ok, cross_k * nk + cross_u * nu + cross_v * nv, 0)
    area = 0.5 * dr.abs(twice)
    return dr.select(good, area, 0)


# --------------------------------------------------------------------------------------------------------
# radius grid


class RadiusGrid:
    """Fixed-radius neighbour search: all stored points within ``radius`` of each query point.

    Layout: cells of side ``radius / subdiv``; points sorted by hash slot (counting sort); a table of
    ``T + 1`` slot start offsets; per stored point one 16-byte packet (x, y, z, original index) read with a
    single packet gather. A query visits the ``(2 subdiv + 1)^3`` cells around its own cell.

    Why 27 cells of side ``r`` (``subdiv=1``) rather than 8 cells of side ``2r``: the 27 cells cover a
    ``3r`` cube (27 r^3, 6.4x the ball) instead of a ``4r`` cube (64 r^3, 15x the ball), and on surfaces
    about 9 r^2 instead of 16 r^2 -- far fewer candidates to test. The usual price, 27 table lookups, is
    cut to 9: a cell's slot is ``row_hash(y, z) + x``, so the 3 cells of an x-row are consecutive slots and
    their points one contiguous range of the sorted array. ``subdiv=2`` (cells of side ``r/2``, 25 rows
    of 5) scans a 2.5 r cube; it pays off only for dense 3D sets.

    Collisions: a slot may hold points of several cells, and two visited rows may share slots. Each
    candidate's cell is recomputed from its stored position (same float ops as at build, so bit-identical)
    and accepted only if it is one of the cells of the row being scanned; the visited cells are distinct,
    so every point is accepted at most once. Within a row the slot range is clipped so that no slot is
    scanned twice even when the table is smaller than a row.

    Memory: 16 B per stored point plus ``4 (T + 1)`` B of table, ``T`` = the next power of two >= the number
    of stored points by default: 20-24 B per point (:meth:`bytes_per_point`). Neighbour lists are extra.

    Attributes: ``size`` (input points), ``count`` (stored = active points), ``radius``, ``cell_size``,
    ``table_size``, ``subdiv``.
    """

    def __init__(
        self,
        points: Any,
        radius: float,
        *,
        active: Any = None,
        table_size: int | None = None,
        subdiv: int = 1,
    ) -> None:
        m = _namespace(type(points))
        self._m = m
        self.radius = _positive("radius", radius)
        if int(subdiv) != subdiv or subdiv < 1:
            raise ValueError(f"RadiusGrid: subdiv must be an integer >= 1, got {subdiv!r}")
        self.subdiv = int(subdiv)
        p = _as_points(m, points)
        n = dr.width(p)
        self.size = n
        act = _mask(m, active, n)
        cell = self.radius / self.subdiv
        self.cell_size = cell
        # float32 inverse cell size, shared bit-for-bit by build and queries
        self._inv = dr.opaque(m.Float, 1.0 / cell)
        self._origin = dr.opaque(m.Array3f, (0.0, 0.0, 0.0))
        if n == 0:
            n_act, lo, hi, bad = 0, [0.0] * 3, [0.0] * 3, 0
        else:
            n_act, lo, hi, bad = _bounds_and_checks(m, p, act, self._origin, self._inv)
        if bad:
            raise ValueError(
                f"RadiusGrid: {bad} active point(s) have NaN/Inf coordinates; exclude them with active=False"
            )
        if n_act:
            _check_cells("radius", lo, hi)
        else:
            lo, hi = [0.0] * 3, [0.0] * 3
        self.count = n_act
        T = _pow2_table("table_size", table_size, n_act)
        self.table_size = T
        self._mask_u = dr.opaque(m.UInt32, T - 1)
        self._T = dr.opaque(m.UInt32, T)
        # query cells are clamped just outside the stored range: no neighbours are lost, and far-away /
        # huge query coordinates never overflow the float -> int conversion
        k = self.subdiv
        self._clamp_lo = dr.opaque(m.Array3f, tuple(v - k - 1 for v in lo))
        self._clamp_hi = dr.opaque(m.Array3f, tuple(v + k + 1 for v in hi))

        if n_act == 0:
            self._start = dr.zeros(m.UInt32, T + 1)
            self._data = dr.zeros(m.Float, 4)
            return
        slot = self._slot_of_points(p)
        slot = dr.select(act, slot, self._T)  # excluded points: sentinel bucket T, sorted last
        dr.eval(slot)
        # histogram -> exclusive prefix sum: start of every slot; stable order from a counting sort
        self._start = _histogram_offsets(m, slot, T)
        perm = counting_sort(slot, T.bit_length())  # values 0..T need bit_length(T) bits
        idx = dr.gather(m.UInt32, perm, dr.arange(m.UInt32, n_act))
        ps = dr.gather(m.Array3f, p, idx)
        data = dr.empty(m.Float, 4 * n_act)
        packet = m.Array4f(ps.x, ps.y, ps.z, dr.reinterpret_array(m.Float, idx))
        dr.scatter(data, packet, dr.arange(m.UInt32, n_act))
        self._data = data
        dr.eval(self._start, self._data)

    # -- internals ----------------------------------------------------------------------------------------

    def _float_cell(self, p: Any) -> Any:
        return dr.floor((p - self._origin) * self._inv)

    def _slot_of_points(self, p: Any) -> Any:
        m = self._m
        c = m.Array3i(self._float_cell(p))
        return (_row_hash(m, c.y, c.z) + _u32(m, c.x)) & self._mask_u

    def nbytes(self) -> int:
        """Bytes held by the grid (sorted point packets + slot table)."""
        return 4 * (dr.width(self._data) + dr.width(self._start))

    def bytes_per_point(self) -> float:
        return self.nbytes() / max(self.count, 1)

    def query_order(self, query: Any) -> Any:
        """A stable permutation that sorts query points by grid slot. Running queries in this order makes
        neighbouring SIMD lanes read the same cells (3-5x faster on LLVM)."""
        m = self._m
        q = _as_points(m, query)
        if dr.width(q) <= 1:
            return dr.arange(m.UInt32, dr.width(q))
        fc = dr.clip(self._float_cell(q), self._clamp_lo, self._clamp_hi)
        fc = dr.select(_isfinite3(q), fc, self._clamp_lo)
        c = m.Array3i(fc)
        slot = (_row_hash(m, c.y, c.z) + _u32(m, c.x)) & self._mask_u
        dr.eval(slot)
        return counting_sort(slot, max(self.table_size - 1, 1).bit_length())

    def _radius2(self, radius: float | None) -> Any:
        r = self.radius if radius is None else _positive("radius", radius)
        if r > self.radius * (1 + 1e-6):
            raise ValueError(f"RadiusGrid: query radius {r} exceeds the build radius {self.radius}")
        return dr.opaque(self._m.Float, min(r, self.radius) ** 2)

    # -- queries ------------------------------------------------------------------------------------------

    def reduce(
        self,
        query: Any,
        body: Callable[..., Any],
        state: Any,
        *,
        radius: float | None = None,
        active: Any = None,
    ) -> Any:
        """Fused neighbour loop: ``state = body(state, j, p_j, d2)`` for every stored point ``j`` (original
        index, UInt32) with ``|p_j - q|^2 = d2 <= radius^2``, per query lane; returns the final state.

        ``state`` is any PyTree of Dr.Jit arrays of the query width (e.g. ``dr.zeros(UInt32, Q)``, or a
        tuple). ``body`` is traced once into a symbolic ``dr.while_loop`` and runs masked (an ``if``), so
        it may also scatter. ``radius`` (default: the build radius) may be smaller than the build radius.
        """
        m = self._m
        q = _as_points(m, query)
        nq = dr.width(q)
        if self.count == 0 or nq == 0:
            return state
        act = _mask(m, active, nq) & _isfinite3(q)
        r2 = self._radius2(radius)
        k = self.subdiv
        L = 2 * k + 1  # cells per row
        R = L * L  # rows
        c = m.Array3i(dr.clip(self._float_cell(q), self._clamp_lo, self._clamp_hi))
        start, data, mask_u, T = self._start, self._data, self._mask_u, self._T
        origin, inv = self._origin, self._inv

        # Outer loop over the rows of the neighbourhood, inner loop over the points of one row's slot
        # range. (A single flat loop that either tests a candidate or advances to the next row was ~30%
        # slower: its row-advance code runs, masked, on every candidate iteration.)
        def row_step(row, st):
            ry = c.y + (m.Int32(row) % L - k)
            rz = c.z + (m.Int32(row) // L - k)
            lo = (_row_hash(m, ry, rz) + _u32(m, c.x - k)) & mask_u
            e = lo + L  # one past the row's last slot, before wrapping around the table
            beg = dr.gather(m.UInt32, start, lo)
            n_main = dr.gather(m.UInt32, start, dr.minimum(e, T)) - beg
            # wrapped part: slots [0, wrap), clipped so that no slot of the row is read twice
            wrap = dr.minimum(dr.select(e > T, e - T, 0), lo)
            total = n_main + dr.gather(m.UInt32, start, wrap)

            def point_step(i, st):
                cur = dr.select(i < n_main, beg + i, i - n_main)
                pkt = dr.gather(m.Array4f, data, cur)  # one packet load: x, y, z, original index
                pj = m.Array3f(pkt.x, pkt.y, pkt.z)
                j = dr.reinterpret_array(m.UInt32, pkt.w)
                cj = m.Array3i(dr.floor((pj - origin) * inv))  # bit-identical to the build's cell
                dv = pj - q
                d2 = dr.dot(dv, dv)
                hit = (cj.y == ry) & (cj.z == rz) & (dr.abs(cj.x - c.x) <= k) & (d2 <= r2)
                st = dr.if_stmt(
                    args=(st, j, pj, d2),
                    cond=hit,
                    true_fn=body,
                    false_fn=lambda s, j_, p_, d_: s,
                    label="RadiusGrid.body",
                )
                return i + 1, st

            _, st = dr.while_loop(
                state=(dr.zeros(m.UInt32, nq), st),
                cond=lambda i, st: i < total,
                body=point_step,
                labels=("i", "state"),
                label="RadiusGrid.points",
            )
            return row + 1, st

        _, st = dr.while_loop(
            state=(dr.zeros(m.UInt32, nq), state),
            cond=lambda row, st: act & (row < R),
            body=row_step,
            labels=("row", "state"),
            label="RadiusGrid.rows",
        )
        return st

    def count_neighbors(self, query: Any, *, radius: float | None = None, active: Any = None) -> Any:
        """Number of stored points within ``radius`` of each query point (UInt32)."""
        m = self._m
        nq = dr.width(query)
        return self.reduce(query, lambda s, j, pj, d2: s + 1, dr.zeros(m.UInt32, nq), radius=radius, active=active)

    def neighbors(self, query: Any, *, radius: float | None = None, active: Any = None) -> tuple[Any, Any]:
        """Explicit neighbour lists, CSR: ``(offsets[Q + 1], indices[offsets[Q]])`` of original point
        indices, for estimators that sweep the same neighbourhoods many times. Two passes of the fused loop
        (count, then fill) with one host sync to size the index array; the order inside a list is the
        deterministic scan order (rows, then slots, then original index)."""
        m = self._m
        nq = dr.width(query)
        counts = self.count_neighbors(query, radius=radius, active=active)
        offsets, total = _csr_from_counts(m, counts)
        indices = dr.zeros(m.UInt32, total)
        if total == 0:
            return offsets, indices
        cursor = dr.gather(m.UInt32, offsets, dr.arange(m.UInt32, nq))

        def fill(s, j, pj, d2):
            dr.scatter(indices, j, s)
            return s + 1

        dr.eval(self.reduce(query, fill, cursor, radius=radius, active=active))
        return offsets, indices


# --------------------------------------------------------------------------------------------------------
# cluster grid


class ClusterGrid:
    """Jittered voxel clusters: every (voxel of side ``h``, coarse normal bin) holding stored points is one
    kernel domain.

    The voxel of ``p`` is ``floor((p - offset) / h)``; ``offset`` (a per-pass jitter, see
    :func:`random_offset`) turns the quantisation into noise across passes. Points are sorted by an
    injective 64-bit key (voxel relative to the lowest occupied voxel, then normal bin) with a counting
    sort, so clusters are contiguous runs: dense ids ``0..C-1`` in key order, CSR member lists with members
    in original-index order. Lookups go through a hash table of the ``C`` cluster keys (counting-sorted by
    slot); a lookup compares the full key of every cluster in its slot, so collisions only cost time.

    Attributes: ``num_clusters`` (C), ``cluster_id`` (UInt32 per input point, :data:`INVALID` for excluded
    points), ``offsets`` (UInt32[C + 1]), ``indices`` (UInt32[count], original indices sorted by cluster),
    ``cluster_cell`` (Array3i[C]), ``cluster_bin`` (UInt32[C]), ``area`` (Float[C], ``A(C)``).
    """

    def __init__(
        self,
        points: Any,
        normals: Any,
        h: float,
        offset: Sequence[float] = (0.0, 0.0, 0.0),
        *,
        active: Any = None,
        normal_bins: int = 6,
        table_size: int | None = None,
        extent_points: Any = None,
    ) -> None:
        m = _namespace(type(points))
        self._m = m
        self.h = _positive("h", h)
        off = tuple(float(v) for v in offset)
        if len(off) != 3 or not all(math.isfinite(v) for v in off):
            raise ValueError(f"ClusterGrid: offset must be 3 finite numbers, got {offset!r}")
        self.offset = off
        if normal_bins not in (1, 6):
            raise ValueError(f"ClusterGrid: normal_bins must be 1 or 6, got {normal_bins}")
        self.normal_bins = normal_bins
        p = _as_points(m, points)
        n = dr.width(p)
        nrm = _as_points(m, normals, n)
        self.size = n
        act = _mask(m, active, n)
        self._origin = dr.opaque(m.Array3f, off)
        self._inv = dr.opaque(m.Float, 1.0 / self.h)
        self._h = dr.opaque(m.Float, self.h)
        if n == 0:
            n_act, lo, hi, bad = 0, [0.0] * 3, [0.0] * 3, 0
        else:
            n_act, lo, hi, bad = _bounds_and_checks(m, p, act, self._origin, self._inv)
        if bad:
            raise ValueError(
                f"ClusterGrid: {bad} active point(s) have NaN/Inf coordinates; exclude them with active=False"
            )
        if n_act:
            _check_cells("h", lo, hi)
        self.count = n_act
        cmin = [int(v) for v in lo] if n_act else [0, 0, 0]
        dims = [int(b) - a + 1 for a, b in zip(cmin, hi, strict=True)] if n_act else [1, 1, 1]
        self._cmin = dr.opaque(m.Array3i, tuple(cmin))
        self._cmax = dr.opaque(m.Array3i, tuple(c + d - 1 for c, d in zip(cmin, dims, strict=True)))
        total = dims[0] * dims[1] * dims[2] * normal_bins
        if total >= 1 << 64:
            raise ValueError(f"ClusterGrid: {total:.3g} possible voxels exceed a 64-bit key; increase h")
        key_bits = max(total, 1).bit_length()  # keys < total, sentinel = total

        if n_act == 0:
            self._empty(T=_pow2_table("table_size", table_size, 1))
            return

        cell = m.Array3i(self._float_cell(p))
        b = normal_bin(nrm, normal_bins)
        rel = cell - self._cmin
        U64 = m.UInt64
        nx = dr.opaque(U64, dims[0])
        ny = dr.opaque(U64, dims[1])
        nb = dr.opaque(U64, normal_bins)
        key = ((U64(rel.z) * ny + U64(rel.y)) * nx + U64(rel.x)) * nb + U64(b)
        key = dr.select(act, key, dr.opaque(U64, total))
        dr.eval(key)
        perm, sorted_key = counting_sort(key, key_bits, with_keys=True)
        i = dr.arange(m.UInt32, n_act)
        idx = dr.gather(m.UInt32, perm, i)  # original indices in cluster order
        sk = dr.gather(U64, sorted_key, i)
        prev = dr.gather(U64, sorted_key, dr.maximum(i, 1) - 1)
        head = (i == 0) | (sk != prev)
        cid_sorted = dr.cumsum(m.UInt32(head)) - 1  # inclusive prefix sum -> dense ids
        dr.eval(cid_sorted, idx)
        C = int(cid_sorted[n_act - 1]) + 1
        self.num_clusters = C
        self._C = dr.opaque(m.UInt32, C)
        self.indices = idx
        cluster_id = dr.full(m.UInt32, INVALID, n)
        dr.scatter(cluster_id, cid_sorted, idx)
        self.cluster_id = cluster_id
        rank = dr.empty(m.UInt32, n)  # each active point's place in cluster order
        dr.scatter(rank, i, idx)
        #: each active point's place in cluster order (others: undefined), and the cluster of each place: a value
        #: per point written to its place is then summed per cluster in order
        self.rank, self.sorted_cluster = rank, cid_sorted
        offsets = dr.opaque(m.UInt32, n_act, C + 1)
        dr.scatter(offsets, i, cid_sorted, head)
        self.offsets = offsets
        # per-cluster key, recomputed from the cluster's first member with the build's own float ops
        first = dr.gather(m.UInt32, idx, dr.gather(m.UInt32, offsets, dr.arange(m.UInt32, C)))
        self.cluster_cell = m.Array3i(self._float_cell(dr.gather(m.Array3f, p, first)))
        self.cluster_bin = normal_bin(dr.gather(m.Array3f, nrm, first), normal_bins)
        dr.eval(self.offsets, self.cluster_id, self.cluster_cell, self.cluster_bin, rank)

        # lookup table: clusters counting-sorted by hash slot
        T = _pow2_table("table_size", table_size, C)
        self.table_size = T
        self._mask_u = dr.opaque(m.UInt32, T - 1)
        cslot = _cell_hash(m, self.cluster_cell, self.cluster_bin) & self._mask_u
        dr.eval(cslot)
        self._slot_start = _histogram_offsets(m, cslot, T)
        self._slot_cluster = counting_sort(cslot, max(T - 1, 1).bit_length())
        extent = None if extent_points is None else act & _mask(m, extent_points, n)
        self.area = self._kernel_area(p, nrm, act, rank, extent)
        dr.eval(self._slot_start, self._slot_cluster, self.area)

    def _empty(self, T: int) -> None:
        m = self._m
        self.num_clusters = 0
        self._C = dr.opaque(m.UInt32, 0)
        self.indices = dr.zeros(m.UInt32, 0)
        self.cluster_id = dr.full(m.UInt32, INVALID, self.size)
        self.offsets = dr.zeros(m.UInt32, 1)
        self.cluster_cell = dr.zeros(m.Array3i, 0)
        self.cluster_bin = dr.zeros(m.UInt32, 0)
        self.area = dr.zeros(m.Float, 0)
        self.table_size = T
        self._mask_u = dr.opaque(m.UInt32, T - 1)
        self._slot_start = dr.zeros(m.UInt32, T + 1)
        self._slot_cluster = dr.zeros(m.UInt32, 0)

    def _float_cell(self, p: Any) -> Any:
        return dr.floor((p - self._origin) * self._inv)

    def _kernel_area(self, p: Any, nrm: Any, member_of: Any, rank: Any, extent: Any = None) -> Any:
        """``A(C)``: area of the cluster's mean plane (through the members' mean point, with their
        normalised mean normal) inside its voxel. The sums run over each cluster's members in pieces
        (:func:`reduce_runs`), whose float atomics may add in another order from build to build: areas agree to
        rounding (the minima, maxima and counts exactly).

        With ``extent`` (a mask of points that sample the surface, each surface point once), the plane is
        also bounded where the surface visibly ends inside the voxel (a wall meeting a corner, an object's
        edge): along each of the two axes across the mean normal, a side of the voxel whose gap to the
        nearest such point exceeds :data:`EDGE_GAPS` mean spacings is moved to one spacing beyond that
        point (the expected gap of uniform points). Clusters of fewer than :data:`EXTENT_MIN_POINTS` such
        points keep the voxel. Without it, ``A(C)`` overestimates the surface in such voxels, and the kernel
        ``1/A(C)`` darkens what the emission technique delivers there (docs/maths.md §5.2).
        """
        m = self._m
        C = self.num_clusters
        cid = dr.arange(m.UInt32, C)
        beg = dr.gather(m.UInt32, self.offsets, cid)
        end = dr.gather(m.UInt32, self.offsets, cid + 1)
        cube_min = self._origin + m.Array3f(self.cluster_cell) * self._h
        centre = cube_min + 0.5 * self._h
        ext = extent if extent is not None else dr.zeros(m.Bool, dr.width(p))
        # each member's point and normal interleaved (the extent flag as the sign of a fourth entry), written in
        # cluster order (``rank``): the sums' loop reads them in order, where reading them at random from inside
        # the loop waited on memory at every step (the writes at random do not wait)
        packed = dr.empty(m.Float, 8 * self.count)
        slot = dr.select(member_of, rank, 0) * 2
        dr.scatter(packed, m.Array4f(p.x, p.y, p.z, dr.select(ext, 1.0, -1.0)), slot, member_of)
        dr.scatter(packed, m.Array4f(nrm.x, nrm.y, nrm.z, 0.0), slot + 1, member_of)
        pieces = run_pieces(self.offsets)
        # relative to the centre of the member's own voxel: the piece's run
        centres = dr.gather(m.Array3f, centre, pieces[0])
        dr.eval(packed, centres)

        def member(i):
            j = i * 2
            pe, nn = dr.gather(m.Array4f, packed, j), dr.gather(m.Array4f, packed, j + 1)
            q = m.Array3f(pe.x, pe.y, pe.z) - centres
            e = pe.w > 0
            return q, m.Array3f(nn.x, nn.y, nn.z), dr.select(e, m.UInt32(1), 0), dr.select(e, q, dr.inf), \
                dr.select(e, q, -dr.inf)

        sp, sn, count, lo, hi = reduce_runs(
            member, (m.Array3f, m.Array3f, m.UInt32, m.Array3f, m.Array3f), pieces, C,
            ops=(dr.ReduceOp.Add, dr.ReduceOp.Add, dr.ReduceOp.Add, dr.ReduceOp.Min, dr.ReduceOp.Max))
        mean = centre + sp / m.Float(end - beg)
        voxel = plane_cube_area(mean, sn, cube_min, self._h)
        if extent is None:
            return voxel
        half = 0.5 * self._h
        a = dr.abs(sn)
        across = [~((a[k] >= a[(k + 1) % 3]) & (a[k] >= a[(k + 2) % 3])) for k in range(3)]  # not the normal axis
        enough = count >= EXTENT_MIN_POINTS
        box_lo, box_hi = [], []
        for k in range(3):
            spacing = (hi[k] - lo[k]) / m.Float(dr.maximum(count, 2) - 1)
            bound = enough & across[k]
            box_lo.append(dr.select(bound & (lo[k] + half > EDGE_GAPS * spacing), dr.maximum(lo[k] - spacing, -half),
                                    -half))
            box_hi.append(dr.select(bound & (half - hi[k] > EDGE_GAPS * spacing), dr.minimum(hi[k] + spacing, half),
                                    half))
        box_min = centre + m.Array3f(*box_lo)
        bounded = plane_box_area(mean, sn, box_min, m.Array3f(*box_hi) - m.Array3f(*box_lo))
        return dr.select(bounded > 0, dr.minimum(bounded, voxel), voxel)

    def nbytes(self) -> int:
        """Bytes held by the cluster structure (per point: id + member index; per cluster: offsets, key,
        area, table entry; plus the slot table)."""
        return 4 * (
            dr.width(self.cluster_id)
            + dr.width(self.indices)
            + dr.width(self.offsets)
            + 3 * dr.width(self.cluster_cell)
            + dr.width(self.cluster_bin)
            + dr.width(self.area)
            + dr.width(self._slot_start)
            + dr.width(self._slot_cluster)
        )

    def bytes_per_point(self) -> float:
        return self.nbytes() / max(self.count, 1)

    def cluster_of(self, query_points: Any, query_normals: Any, active: Any = None) -> Any:
        """Cluster id (UInt32) of each query (point, normal), or :data:`INVALID` when no stored point lies
        in that (voxel, normal bin). Non-finite query points get :data:`INVALID`."""
        m = self._m
        q = _as_points(m, query_points)
        nq = dr.width(q)
        qn = _as_points(m, query_normals, nq)
        if self.num_clusters == 0 or nq == 0:
            return dr.full(m.UInt32, INVALID, nq)
        fc = self._float_cell(q)
        act = _mask(m, active, nq) & _isfinite3(q)
        # voxels outside the occupied range hold no cluster; this also keeps the int conversion in range
        lo, hi = m.Array3f(self._cmin), m.Array3f(self._cmax)
        act &= dr.all((fc >= lo) & (fc <= hi))
        c = m.Array3i(dr.clip(fc, lo, hi))
        b = normal_bin(qn, self.normal_bins)
        slot = _cell_hash(m, c, b) & self._mask_u
        i = dr.gather(m.UInt32, self._slot_start, slot, act)
        end = dr.gather(m.UInt32, self._slot_start, slot + 1, act)
        cells, bins, slot_cluster = self.cluster_cell, self.cluster_bin, self._slot_cluster

        def body(i, found):
            cand = dr.gather(m.UInt32, slot_cluster, i)
            same = (dr.gather(m.Array3i, cells, cand) == c) & (dr.gather(m.UInt32, bins, cand) == b)
            return i + 1, dr.select(dr.all(same), cand, found)

        _, found = dr.while_loop(
            state=(dr.select(act, i, 0), dr.full(m.UInt32, INVALID, nq)),
            cond=lambda i, found: act & (i < end) & (found == INVALID),
            body=body,
            label="ClusterGrid.cluster_of",
        )
        return found

    def reduce_ids(self, cluster_ids: Any, body: Callable[..., Any], state: Any, active: Any = None) -> Any:
        """Fused member loop: ``state = body(state, j)`` for every member ``j`` (original index) of cluster
        ``cluster_ids[lane]``; lanes with :data:`INVALID` keep their state."""
        m = self._m
        cid = m.UInt32(cluster_ids)
        nq = dr.width(cid)
        if self.num_clusters == 0 or nq == 0:
            return state
        act = _mask(m, active, nq) & (cid < self._C)
        beg = dr.gather(m.UInt32, self.offsets, cid, act)
        end = dr.gather(m.UInt32, self.offsets, cid + 1, act)
        idx = self.indices

        def step(i, st):
            j = dr.gather(m.UInt32, idx, i)
            return i + 1, body(st, j)

        _, st = dr.while_loop(
            state=(dr.select(act, beg, 0), state),
            cond=lambda i, st: act & (i < end),
            body=step,
            label="ClusterGrid.reduce",
        )
        return st

    def reduce(
        self, query_points: Any, query_normals: Any, body: Callable[..., Any], state: Any, active: Any = None
    ) -> Any:
        """``reduce_ids(cluster_of(query_points, query_normals), body, state)``."""
        return self.reduce_ids(self.cluster_of(query_points, query_normals, active), body, state)

    def neighbors(self, cluster_ids: Any) -> tuple[Any, Any]:
        """Per-query explicit lists (CSR ``offsets[Q + 1]``, ``indices``) of the members of each query's
        cluster. Usually the cluster CSR itself (``self.offsets``, ``self.indices``) indexed by cluster id is
        all an estimator needs; this expands it per query for code that wants one list per lane."""
        m = self._m
        cid = m.UInt32(cluster_ids)
        nq = dr.width(cid)
        ok = cid < self._C if self.num_clusters else dr.zeros(m.Bool, nq)
        counts = dr.select(
            ok, dr.gather(m.UInt32, self.offsets, cid + 1, ok) - dr.gather(m.UInt32, self.offsets, cid, ok), 0
        )
        offsets, total = _csr_from_counts(m, counts)
        indices = dr.zeros(m.UInt32, total)
        if total == 0:
            return offsets, indices
        cursor = dr.gather(m.UInt32, offsets, dr.arange(m.UInt32, nq))

        def fill(s, j):
            dr.scatter(indices, j, s)
            return s + 1

        dr.eval(self.reduce_ids(cid, fill, cursor))
        return offsets, indices
