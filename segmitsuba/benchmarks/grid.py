"""Benchmark of the hash grids (``python -m segmitsuba.benchmarks.grid [--n N] [--reps R] [--neighbors K]``).

Points lie on a few planes (a floor, two walls, a tilted panel and a box top), like surface hits, with
density weighted by area; the radius is chosen for ``K`` neighbours per query on average. Every number is
warm: each operation runs once to compile its kernels, then the median of ``R`` timed runs (each closed
with ``dr.sync_thread()``, since launches are asynchronous) is reported.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import drjit as dr  # importing this module imported `segmitsuba` first, which set up libLLVM
import drjit.llvm.ad as m

from segmitsuba.grid import ClusterGrid, RadiusGrid, random_offset

#: (origin, edge u, edge v) of the parallelograms the points lie on
PLANES = (
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # floor
    ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),  # wall x = 0
    ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # wall y = 1
    ((0.2, 0.2, 0.1), (0.6, 0.0, 0.3), (0.0, 0.6, 0.3)),  # tilted panel
    ((0.5, 0.5, 0.4), (0.3, 0.0, 0.0), (0.0, 0.3, 0.0)),  # box top
)


def _area(u: tuple[float, ...], v: tuple[float, ...]) -> float:
    c = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
    return math.sqrt(sum(x * x for x in c))


def surface_points(n: int, seed: int) -> tuple[Any, Any, float]:
    """``n`` points on :data:`PLANES` (uniform by area) with their normals, and the total area."""
    areas = [_area(u, v) for _, u, v in PLANES]
    total = sum(areas)
    rng = m.PCG32(n, seed)
    pick, s, t = rng.next_float32() * total, rng.next_float32(), rng.next_float32()
    p = dr.zeros(m.Array3f, n)
    nrm = dr.zeros(m.Array3f, n)
    acc = 0.0
    for (o, u, v), a in zip(PLANES, areas, strict=True):
        sel = pick >= acc
        pp = m.Array3f(*o) + s * m.Array3f(*u) + t * m.Array3f(*v)
        nn = dr.normalize(dr.cross(m.Array3f(*u), m.Array3f(*v)))
        # alternate the facing so both sides of the surfaces show up, as with real hits
        nn = dr.select((dr.arange(m.UInt32, n) & 1) == 1, -nn, nn)
        p = dr.select(sel, pp, p)
        nrm = dr.select(sel, nn, nrm)
        acc += a
    dr.eval(p, nrm)
    return p, nrm, total


def _time(fn: Callable[[], Any], reps: int) -> float:
    dr.eval(fn())  # warm-up: compile
    dr.sync_thread()
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        dr.eval(fn())
        dr.sync_thread()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def run(args: list[str] | None = None) -> str:
    """Run the benchmark and return its table (``main`` prints it)."""
    ap = argparse.ArgumentParser(prog="segmitsuba.benchmarks.grid", description=__doc__)
    ap.add_argument("--n", type=int, default=1_000_000, help="stored points and queries")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--neighbors", type=float, default=32.0, help="target mean neighbour count")
    ap.add_argument("--subdiv", type=int, default=1)
    a = ap.parse_args(args)

    n = a.n
    pts, nrm, area = surface_points(n, 1)
    qry, _, _ = surface_points(n, 2)
    r = math.sqrt(a.neighbors * area / (math.pi * n))
    rows: list[tuple[str, str]] = []

    def build() -> Any:
        return RadiusGrid(pts, r, subdiv=a.subdiv)._data

    t_build = _time(build, a.reps)
    grid = RadiusGrid(pts, r, subdiv=a.subdiv)
    t_order = _time(lambda: grid.query_order(qry), a.reps)
    order = grid.query_order(qry)
    qs = dr.gather(m.Array3f, qry, order)
    dr.eval(qs)
    counts = grid.count_neighbors(qs)
    mean_k = dr.mean(m.Float(counts))[0]
    t_count = _time(lambda: grid.count_neighbors(qs), a.reps)
    t_count_unsorted = _time(lambda: grid.count_neighbors(qry), max(1, a.reps // 2))

    def sum_d2() -> Any:
        return grid.reduce(qs, lambda s, j, pj, d2: s + d2, dr.zeros(m.Float, n))

    t_sum = _time(sum_d2, a.reps)
    t_lists = _time(lambda: grid.neighbors(qs)[1], a.reps)

    h = 2.0 * r
    off = random_offset(h, 7)

    def cbuild() -> Any:
        return ClusterGrid(pts, nrm, h, off).area

    t_cbuild = _time(cbuild, a.reps)
    cg = ClusterGrid(pts, nrm, h, off)
    t_lookup = _time(lambda: cg.cluster_of(qry, nrm), a.reps)

    ms = 1e3
    rows += [
        ("radius", f"r = {r:.4g}, subdiv {a.subdiv}, table {grid.table_size}, mean neighbours {mean_k:.1f}"),
        ("build (RadiusGrid)", f"{t_build * ms:8.1f} ms   (target <= 50 ms at 1e6)"),
        ("query order (sort by cell)", f"{t_order * ms:8.1f} ms"),
        ("count, sorted queries", f"{t_count * ms:8.1f} ms   (target <= 400 ms at 1e6)"),
        ("count, unsorted queries", f"{t_count_unsorted * ms:8.1f} ms"),
        ("fused sum of d2, sorted", f"{t_sum * ms:8.1f} ms"),
        ("neighbour lists (CSR)", f"{t_lists * ms:8.1f} ms   ({int(dr.sum(counts)[0])} entries)"),
        ("RadiusGrid bytes / point", f"{grid.bytes_per_point():8.1f} B    (target <= 40 B)"),
        ("cluster h / clusters", f"h = {h:.4g}, C = {cg.num_clusters} ({cg.count / max(cg.num_clusters, 1):.1f} pts)"),
        ("cluster build (+ A(C))", f"{t_cbuild * ms:8.1f} ms"),
        ("cluster_of lookups", f"{t_lookup * ms:8.1f} ms"),
        ("ClusterGrid bytes / point", f"{cg.bytes_per_point():8.1f} B"),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"hash grid benchmark: N = Q = {n}, {dr.thread_count()} threads, LLVM {dr.detail.llvm_version()}"]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    return "\n".join(lines)


def main() -> None:
    print(run())


if __name__ == "__main__":
    main()
