"""Hash grids against brute force (NumPy, float64) on small sets: radius search, clusters, kernel areas,
collisions, degenerate inputs, invalid inputs, and "no new kernels when only scalars change"."""

from __future__ import annotations

import math

import drjit as dr  # conftest imported segmitsuba (libLLVM set-up) before this module
import mitsuba as mi
import numpy as np
import pytest

from segmitsuba.grid import (
    INVALID,
    ClusterGrid,
    RadiusGrid,
    counting_sort,
    normal_bin,
    plane_cube_area,
    reduce_runs,
    run_pieces,
)


def P3(a: np.ndarray) -> mi.Point3f:
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return mi.Point3f(np.ascontiguousarray(a.T)) if len(a) else dr.zeros(mi.Point3f, 0)


def V3(a: np.ndarray) -> mi.Vector3f:
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return mi.Vector3f(np.ascontiguousarray(a.T)) if len(a) else dr.zeros(mi.Vector3f, 0)


# ------------------------------------------------------------------------------------------------- data


def uniform(rng, n):
    return rng.random((n, 3)).astype(np.float32)


def on_planes(rng, n):
    """Points on a floor, a wall and a tilted panel, like surface hits."""
    s, t = rng.random(n), rng.random(n)
    k = rng.integers(0, 3, n)
    p = np.where(
        (k == 0)[:, None],
        np.stack([s, t, np.full(n, 0.25)], 1),
        np.where((k == 1)[:, None], np.stack([np.zeros(n), s, t], 1), np.stack([s, 0.3 + 0.4 * t, 0.2 + 0.4 * t], 1)),
    )
    return p.astype(np.float32)


def single_plane(rng, n):
    p = rng.random((n, 3)).astype(np.float32)
    p[:, 2] = 0.3  # degenerate bounding box
    return p


def one_cell(rng, n):
    return (0.51 + 0.01 * rng.random((n, 3))).astype(np.float32)


# ------------------------------------------------------------------------------------------------- radius


def brute_radius(P, Q, r, active=None):
    """Per query: (certain neighbours, ambiguous ones within 1e-5 relative of r^2 -- float32 rounding)."""
    P64, Q64 = P.astype(np.float64), Q.astype(np.float64)
    if len(P) == 0:
        return [(set(), set()) for _ in range(len(Q))]
    d2 = ((Q64[:, None, :] - P64[None, :, :]) ** 2).sum(-1)
    if active is not None:
        d2[:, ~active] = np.inf
    r2 = r * r
    inside = d2 < r2 * (1 - 1e-5)
    amb = np.abs(d2 - r2) <= r2 * 1e-5
    return [(set(np.nonzero(inside[q])[0].tolist()), set(np.nonzero(amb[q])[0].tolist())) for q in range(len(Q))]


def check_lists(offsets, indices, ref):
    off = offsets.numpy()
    idx = indices.numpy()
    assert off[0] == 0 and len(off) == len(ref) + 1 and off[-1] == len(idx)
    for q, (must, maybe) in enumerate(ref):
        got = idx[off[q] : off[q + 1]].tolist()
        assert len(got) == len(set(got)), f"query {q}: a neighbour was reported twice"
        got = set(got)
        assert must <= got and got <= must | maybe, f"query {q}: {sorted(got ^ must)}"


@pytest.mark.parametrize(
    "gen,n,r,table,subdiv",
    [
        (uniform, 1500, 0.09, None, 1),
        (uniform, 1500, 0.09, 1, 1),  # every cell collides in one slot
        (uniform, 1500, 0.09, 4, 2),  # rows longer than the table
        (on_planes, 2000, 0.06, None, 1),
        (on_planes, 2000, 0.06, 2, 1),
        (on_planes, 2000, 0.06, 64, 2),
        (single_plane, 1000, 0.08, None, 1),
        (one_cell, 300, 0.1, None, 1),
        (one_cell, 300, 0.1, 1, 2),
        (uniform, 1, 0.2, None, 1),
        (uniform, 0, 0.2, None, 1),
    ],
)
def test_radius_matches_brute_force(gen, n, r, table, subdiv):
    rng = np.random.default_rng(n + (table or 0) + 17 * subdiv)
    P = gen(rng, n)
    Q = np.concatenate([gen(rng, 200), P[:50], np.array([[5.0, 5.0, 5.0], [-3.0, 0.5, 0.5]], np.float32)])
    grid = RadiusGrid(P3(P), r, table_size=table, subdiv=subdiv)
    assert grid.count == n
    ref = brute_radius(P, Q, r)
    offsets, indices = grid.neighbors(P3(Q))
    check_lists(offsets, indices, ref)
    counts = grid.count_neighbors(P3(Q)).numpy()
    assert np.array_equal(counts, np.diff(offsets.numpy()))
    # fused reduction with a tuple state: sum of d2 and the largest neighbour index
    nq = len(Q)
    s, mx = grid.reduce(
        P3(Q),
        lambda st, j, pj, d2: (st[0] + d2, dr.maximum(st[1], j + 1)),
        (dr.zeros(mi.Float, nq), dr.zeros(mi.UInt32, nq)),
    )
    P64 = P.astype(np.float64)
    off, idx = offsets.numpy(), indices.numpy()
    for q in range(nq):
        mem = idx[off[q] : off[q + 1]]
        ref_s = ((P64[mem] - Q[q].astype(np.float64)) ** 2).sum()
        assert abs(s.numpy()[q] - ref_s) <= 1e-4 * max(1.0, ref_s)
        assert mx.numpy()[q] == (mem.max() + 1 if len(mem) else 0)


def test_radius_smaller_query_radius_order_and_determinism():
    rng = np.random.default_rng(3)
    P, Q = on_planes(rng, 1500), on_planes(rng, 300)
    g1 = RadiusGrid(P3(P), 0.08)
    check_lists(*g1.neighbors(P3(Q), radius=0.05), brute_radius(P, Q, 0.05))
    with pytest.raises(ValueError):
        g1.neighbors(P3(Q), radius=0.1)
    # reproducible builds: identical lists, in identical order
    g2 = RadiusGrid(P3(P), 0.08)
    a, b = g1.neighbors(P3(Q))[1].numpy(), g2.neighbors(P3(Q))[1].numpy()
    assert np.array_equal(a, b)
    # sorting queries by cell permutes the results and nothing else
    order = g1.query_order(P3(Q)).numpy()
    assert sorted(order.tolist()) == list(range(len(Q)))
    c = g1.count_neighbors(P3(Q)).numpy()
    cs = g1.count_neighbors(P3(Q[order])).numpy()
    assert np.array_equal(c[order], cs)


def test_radius_active_mask_and_invalid_queries():
    rng = np.random.default_rng(4)
    P = uniform(rng, 800)
    active = rng.random(800) < 0.7
    P[~active][:10] = np.nan  # excluded points may be garbage
    P[np.nonzero(~active)[0][:10]] = np.nan
    grid = RadiusGrid(P3(P), 0.1, active=mi.Bool(active))
    assert grid.count == int(active.sum())
    Q = uniform(rng, 200)
    check_lists(*grid.neighbors(P3(Q)), brute_radius(np.nan_to_num(P, nan=9.0), Q, 0.1, active))
    bad_q = np.array([[np.nan, 0.5, 0.5], [np.inf, 0.5, 0.5], [0.5, -np.inf, 0.5], [1e30, 1e30, -1e30]], np.float32)
    assert grid.count_neighbors(P3(bad_q)).numpy().tolist() == [0, 0, 0, 0]


def test_invalid_input_raises():
    rng = np.random.default_rng(5)
    P = uniform(rng, 50)
    for r in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            RadiusGrid(P3(P), r)
        with pytest.raises(ValueError):
            ClusterGrid(P3(P), V3(P), r)
    for bad in (np.nan, np.inf, -np.inf):
        Pb = P.copy()
        Pb[7, 1] = bad
        with pytest.raises(ValueError, match="NaN/Inf"):
            RadiusGrid(P3(Pb), 0.1)
        with pytest.raises(ValueError, match="NaN/Inf"):
            ClusterGrid(P3(Pb), V3(P), 0.1)
    with pytest.raises(ValueError):
        RadiusGrid(P3(P), 0.1, table_size=3)
    with pytest.raises(ValueError):
        ClusterGrid(P3(P), V3(P), 0.1, (0.0, float("nan"), 0.0))
    with pytest.raises(ValueError):
        RadiusGrid(P3(P * 1e6), 1e-3)  # cells beyond float32 resolution


# ------------------------------------------------------------------------------------------------ cluster


def brute_clusters(P, Nrm, h, off, bins, active=None):
    """{(voxel, bin): [indices]} with the grid's own float32 arithmetic."""
    cell = np.floor((P - np.asarray(off, np.float32)) * np.float32(1.0 / h)).astype(np.int64)
    a = np.abs(Nrm)
    ax = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0, np.where(a[:, 1] >= a[:, 2], 1, 2))
    b = 2 * ax + (Nrm[np.arange(len(Nrm)), ax] < 0) if bins == 6 else np.zeros(len(P), np.int64)
    groups: dict = {}
    for i in range(len(P)):
        if active is None or active[i]:
            groups.setdefault((tuple(cell[i]), int(b[i])), []).append(i)
    return groups, cell, b


def check_clusters(g, P, Nrm, h, off, bins, active=None):
    groups, cell, b = brute_clusters(P, Nrm, h, off, bins, active)
    cid, offs, ind = g.cluster_id.numpy(), g.offsets.numpy(), g.indices.numpy()
    assert g.num_clusters == len(groups)
    assert offs[0] == 0 and offs[-1] == len(ind) == g.count
    got = {}
    for c in range(g.num_clusters):
        mem = ind[offs[c] : offs[c + 1]].tolist()
        assert mem == sorted(mem) and len(mem) > 0
        got[(tuple(cell[mem[0]]), int(b[mem[0]]))] = mem
        assert all(cid[j] == c for j in mem)
        assert tuple(g.cluster_cell.numpy()[:, c]) == tuple(cell[mem[0]])
    assert got == groups
    if active is not None:
        assert (cid[~active] == INVALID).all()
    return groups


@pytest.mark.parametrize(
    "gen,n,h,table,bins",
    [
        (uniform, 2000, 0.15, None, 6),
        (uniform, 2000, 0.15, 1, 6),
        (on_planes, 2000, 0.1, 8, 6),
        (on_planes, 2000, 0.1, None, 1),
        (single_plane, 500, 0.2, None, 6),
        (one_cell, 300, 0.5, 2, 6),
        (uniform, 1, 0.1, None, 6),
        (uniform, 0, 0.1, None, 6),
    ],
)
def test_clusters_match_brute_force(gen, n, h, table, bins):
    rng = np.random.default_rng(n + 3 * (table or 0) + bins)
    P = gen(rng, n)
    Nrm = rng.normal(size=(n, 3)).astype(np.float32)
    off = tuple(rng.random(3) * h)
    g = ClusterGrid(P3(P), V3(Nrm), h, off, normal_bins=bins, table_size=table)
    groups = check_clusters(g, P, Nrm, h, off, bins)
    # lookups: the stored points find their own cluster; random queries agree with brute force
    assert np.array_equal(g.cluster_of(P3(P), V3(Nrm)).numpy(), g.cluster_id.numpy())
    Q = np.concatenate([uniform(rng, 300) * 1.2 - 0.1, P[:20]])
    Qn = rng.normal(size=(len(Q), 3)).astype(np.float32)
    look = g.cluster_of(P3(Q), V3(Qn)).numpy()
    qg, qcell, qb = brute_clusters(Q, Qn, h, off, bins)
    ids = {k: g.cluster_id.numpy()[v[0]] for k, v in groups.items()}
    for i in range(len(Q)):
        assert look[i] == ids.get((tuple(qcell[i]), int(qb[i])), INVALID)
    # fused member loop and explicit per-query lists
    sizes = np.diff(g.offsets.numpy())
    cnt = g.reduce(P3(Q), V3(Qn), lambda s, j: s + 1, dr.zeros(mi.UInt32, len(Q))).numpy()
    assert cnt.tolist() == [0 if c == INVALID else int(sizes[c]) for c in look]
    qo, qi = g.neighbors(mi.UInt32(look))
    qo, qi, ind, offs = qo.numpy(), qi.numpy(), g.indices.numpy(), g.offsets.numpy()
    for i in range(len(Q)):
        exp = [] if look[i] == INVALID else ind[offs[look[i]] : offs[look[i] + 1]].tolist()
        assert qi[qo[i] : qo[i + 1]].tolist() == exp


def test_cluster_walls_jitter_mask_and_invalid_queries():
    rng = np.random.default_rng(8)
    # a thin wall: the two faces are 2e-4 apart, in the same voxels, with opposite normals
    s = rng.random((400, 2)).astype(np.float32)
    front = np.stack([np.full(400, 0.5001), s[:, 0], s[:, 1]], 1).astype(np.float32)
    back = np.stack([np.full(400, 0.4999), s[:, 0], s[:, 1]], 1).astype(np.float32)
    P = np.concatenate([front, back])
    Nrm = np.concatenate([np.tile([1.0, 0.0, 0.0], (400, 1)), np.tile([-1.0, 0.0, 0.0], (400, 1))]).astype(np.float32)
    g = ClusterGrid(P3(P), V3(Nrm), 0.25, (0.1, 0.1, 0.1))
    cid = g.cluster_id.numpy()
    assert not set(cid[:400]) & set(cid[400:])
    g1 = ClusterGrid(P3(P), V3(Nrm), 0.25, (0.1, 0.1, 0.1), normal_bins=1)
    assert g1.num_clusters < g.num_clusters
    # jitter changes the partition
    g2 = ClusterGrid(P3(P), V3(Nrm), 0.25, (0.2, 0.05, 0.17))

    def part(gr):
        o = gr.offsets.numpy()
        return {tuple(gr.indices.numpy()[a:b]) for a, b in zip(o[:-1], o[1:], strict=True)}

    assert part(g) != part(g2)
    # excluded points (even NaN ones) are in no cluster
    P2 = uniform(rng, 600)
    N2 = rng.normal(size=(600, 3)).astype(np.float32)
    act = rng.random(600) < 0.6
    P2[np.nonzero(~act)[0][:5]] = np.nan
    g3 = ClusterGrid(P3(P2), V3(N2), 0.2, (0.03, 0.0, 0.11), active=mi.Bool(act))
    check_clusters(g3, np.nan_to_num(P2), N2, 0.2, (0.03, 0.0, 0.11), 6, act)
    bad = np.array([[np.nan, 0.5, 0.5], [np.inf, 0.1, 0.1], [1e30, 0, 0], [50.0, 50.0, 50.0]], np.float32)
    assert (g3.cluster_of(P3(bad), V3(np.ones((4, 3)))).numpy() == INVALID).all()


def test_normal_bin_opposite_normals_differ():
    rng = np.random.default_rng(9)
    n = rng.normal(size=(500, 3)).astype(np.float32)
    n[:3] = [[1, 1, 0], [0, -1, 1], [1, 1, 1]]  # ties
    a = normal_bin(V3(n)).numpy()
    b = normal_bin(V3(-n)).numpy()
    assert (a != b).all() and (a // 2 == b // 2).all() and a.max() < 6


# ------------------------------------------------------------------------------------------------ areas


def ref_area(p, n, cmin, h):
    """Polygon of the plane cut through the 12 cube edges, sorted by angle, shoelace (float64)."""
    p, n, cmin = (np.asarray(v, np.float64) for v in (p, n, cmin))
    nl = np.linalg.norm(n)
    if not nl > 0:
        return h * h
    n = n / nl
    d = n @ p
    corners = [cmin + h * np.array([i, j, k], np.float64) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    pts = []
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") != 1:
                continue
            fa, fb = n @ corners[a] - d, n @ corners[b] - d
            if fa == 0:
                pts.append(corners[a])
            if fb == 0:
                pts.append(corners[b])
            if fa * fb < 0:
                pts.append(corners[a] + fa / (fa - fb) * (corners[b] - corners[a]))
    if len(pts) < 3:
        return h * h
    pts = np.array(pts)
    c = pts.mean(0)
    u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    x, y = (pts - c) @ u, (pts - c) @ v
    o = np.argsort(np.arctan2(y, x))
    x, y = x[o], y[o]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return area if area > 0 else h * h


def test_plane_cube_area_against_reference():
    rng = np.random.default_rng(10)
    m = 600
    h = rng.uniform(0.1, 3.0, m)
    cmin = rng.uniform(-5, 5, (m, 3))
    p = cmin + h[:, None] * rng.random((m, 3))
    n = rng.normal(size=(m, 3))
    n[:40] = np.eye(3)[rng.integers(0, 3, 40)] * rng.choice([-1, 1], (40, 1))  # axis-aligned
    n[40:80, rng.integers(0, 3)] = 0  # normals in a coordinate plane
    p[80:100] = cmin[80:100] + h[80:100, None] * rng.choice([0.02, 0.98], (20, 3))  # corner cuts
    got = plane_cube_area(P3(p), V3(n), P3(cmin), mi.Float(h.astype(np.float32))).numpy()
    ref = np.array([ref_area(p[i], n[i], cmin[i], h[i]) for i in range(m)])
    assert np.allclose(got, ref, rtol=2e-4, atol=1e-4 * h**2), np.abs(got - ref).max()


def test_plane_cube_area_known_values():
    # cube [0, 2]^3; cases where polygon edges lie on cube edges or the plane lies on a face
    cases = [
        ((1, 1, 1), (0, 0, 1), 4.0),
        ((1, 1, 1), (1, 1, 0), 4.0 * math.sqrt(2)),  # through two opposite cube edges
        ((1, 1, 1), (1, -1, 0), 4.0 * math.sqrt(2)),
        ((1, 1, 1), (1, 1, 1), 3 * math.sqrt(3) / 4 * 4.0),  # regular hexagon
        ((0, 1, 1), (1, 0, 0), 4.0),  # on the face x = 0
        ((1, 2, 1), (0, -1, 0), 4.0),  # on the face y = 2
        ((1, 1, 2), (0, 0, 1), 4.0),  # on the face z = 2
        ((2, 0, 0), (1, 1, 1), 0.5 * math.sqrt(3) * (2 * math.sqrt(2)) ** 2 / 2),  # corner triangle
        ((1, 1, 1), (0, 0, 0), 4.0),  # zero normal -> h^2
        ((3, 3, 3), (1, 2, 3), 4.0),  # misses the cube -> h^2
        ((0, 0, 1), (1, 1, 0), 4.0),  # touches only the edge x = y = 0 -> area 0 -> h^2
    ]
    p = [c[0] for c in cases]
    n = [c[1] for c in cases]
    got = plane_cube_area(P3(p), V3(n), P3(np.zeros((len(cases), 3))), 2.0).numpy()
    exp = [c[2] for c in cases]
    assert np.allclose(got, exp, rtol=1e-5), (got, exp)


def test_cluster_kernel_area_is_mean_plane_area():
    rng = np.random.default_rng(11)
    P, h, off = on_planes(rng, 1500), 0.2, (0.07, 0.02, 0.13)
    Nrm = rng.normal(size=(1500, 3)).astype(np.float32) * 0.3 + np.array([0, 0, 1], np.float32)
    g = ClusterGrid(P3(P), V3(Nrm), h, off)
    offs, ind, area = g.offsets.numpy(), g.indices.numpy(), g.area.numpy()
    cells = g.cluster_cell.numpy().T
    for c in range(g.num_clusters):
        mem = ind[offs[c] : offs[c + 1]]
        cmin = np.asarray(off) + cells[c] * h
        ref = ref_area(P[mem].astype(np.float64).mean(0), Nrm[mem].astype(np.float64).sum(0), cmin, h)
        assert abs(area[c] - ref) <= 2e-3 * h * h, (c, area[c], ref)


# ------------------------------------------------------------------------------------------- compilation


def test_new_scalars_compile_no_new_kernels():
    """Second build + queries with other N, radius, h, jitter and table size: every JIT kernel launched
    has a hash already seen in the first round (``cache_hit`` alone also counts disk-cache hits)."""
    rng = np.random.default_rng(12)

    def data(n):
        P, Nrm = P3(on_planes(rng, n)), V3(rng.normal(size=(n, 3)))
        dr.eval(P, Nrm)
        return P, Nrm

    def work(P, Nrm, r, h, off, table):
        n = dr.width(P)
        g = RadiusGrid(P, r, table_size=table)
        out = list(g.neighbors(P))
        out.append(g.reduce(P, lambda s, j, pj, d2: s + d2, dr.zeros(mi.Float, n)))
        out.append(g.query_order(P))
        cg = ClusterGrid(P, Nrm, h, off, table_size=table)
        ids = cg.cluster_of(P, Nrm)
        out += [cg.area, ids, *cg.neighbors(ids)]
        dr.eval(out)
        dr.sync_thread()

    def hashes():
        return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}

    first, second = data(3000), data(1234)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
        dr.kernel_history_clear()
        work(*first, 0.05, 0.1, (0.01, 0.02, 0.03), None)
        seen = hashes()
        work(*second, 0.031, 0.073, (0.05, 0.004, 0.06), 64)
        new = hashes() - seen
    assert seen and not new


@pytest.mark.parametrize("counts", [[], [1], [5, 0, 70, 1, 1, 0, 33, 64, 2], [200], [0, 0, 3]])
def test_reduce_runs_reduces_every_run_in_pieces(counts):
    """Sums, minima and maxima over runs shorter than, equal to and longer than a piece, runs without entries
    (the identity) and no entries at all."""
    rng = np.random.default_rng(14)
    a, b = rng.normal(size=sum(counts)).astype(np.float32), rng.random(sum(counts)).astype(np.float32)
    fa, fb = mi.Float(a), mi.Float(b)
    offsets = mi.UInt32(np.concatenate([[0], np.cumsum(counts)]).astype(np.uint32))
    pieces = run_pieces(offsets, piece=16)
    assert np.all(np.array(pieces[2]) - np.array(pieces[1]) <= 16)
    total, twice, least, most = reduce_runs(
        lambda i: (dr.gather(mi.Float, fa, i), dr.gather(mi.Float, fb, i) * 2, dr.gather(mi.Float, fa, i),
                   dr.gather(mi.Float, fa, i)),
        (mi.Float,) * 4, pieces, len(counts), ops=(dr.ReduceOp.Add, dr.ReduceOp.Add, dr.ReduceOp.Min, dr.ReduceOp.Max))
    runs = np.split(a, np.cumsum(counts))[: len(counts)]
    twice_runs = np.split(2 * b, np.cumsum(counts))[: len(counts)]
    assert np.allclose(np.array(total), [r.astype(np.float64).sum() for r in runs], rtol=1e-5, atol=1e-5)
    assert np.allclose(np.array(twice), [r.astype(np.float64).sum() for r in twice_runs], rtol=1e-5, atol=1e-5)
    assert np.array_equal(np.array(least), [r.min() if len(r) else np.inf for r in runs])
    assert np.array_equal(np.array(most), [r.max() if len(r) else -np.inf for r in runs])


def test_memory_per_point():
    rng = np.random.default_rng(13)
    P = on_planes(rng, 5000)
    g = RadiusGrid(P3(P), 0.05)
    assert g.bytes_per_point() <= 40
    cg = ClusterGrid(P3(P), V3(rng.normal(size=(5000, 3))), 0.01)
    assert cg.bytes_per_point() <= 48  # worst case (every point its own cluster) is 44 + table


def test_cluster_area_follows_the_surface_where_it_ends_in_the_voxel():
    """With surface points, A(C) is the part of the mean plane that the surface covers: a floor that ends
    half-way across its voxel (a wall corner, an object's edge) has about half the voxel's area; a floor
    across the whole voxel keeps it."""
    rng = np.random.default_rng(5)
    h, count = 1.0, 60
    for cover in (1.0, 0.5, 0.25):
        pts = np.stack([rng.uniform(0, cover, count), rng.uniform(0, 1, count), np.full(count, 0.4)], 1)
        pts = (pts * h + 1e-4).astype(np.float32)
        nrm = np.tile(np.array([0, 0, 1], np.float32), (count, 1))
        g = ClusterGrid(P3(pts), V3(nrm), h, (0.0, 0.0, 0.0), extent_points=mi.Bool([True] * count))
        plain = ClusterGrid(P3(pts), V3(nrm), h, (0.0, 0.0, 0.0))
        assert g.num_clusters == 1
        assert plain.area.numpy()[0] == pytest.approx(h * h, rel=1e-5)  # the voxel's cut, whatever the cover
        assert g.area.numpy()[0] == pytest.approx(cover * h * h, rel=0.08), cover
    few = ClusterGrid(P3(pts[:5]), V3(nrm[:5]), h, (0.0, 0.0, 0.0), extent_points=mi.Bool([True] * 5))
    assert few.area.numpy()[0] == pytest.approx(h * h, rel=1e-5)  # too few points to tell an edge from noise


@pytest.mark.parametrize("bits", [1, 9, 16, 17, 25, 33, 40])
def test_counting_sort_is_a_stable_sort(bits):
    """One radix pass up to the widest digit, several of equal digits beyond (docs/maths.md §4.4): the permutation
    is numpy's stable argsort of the keys (below ``2^bits``, 32- and 64-bit), with many equal keys."""
    rng = np.random.default_rng(bits)
    n = 50000
    wide = bits > 32
    keys = rng.integers(0, 1 << bits, n, dtype=np.uint64)
    keys &= ~np.uint64(0xF) if bits > 8 else ~np.uint64(0)  # equal keys, whose input order a stable sort keeps
    tp, dt = (mi.UInt64, np.uint64) if wide else (mi.UInt32, np.uint32)
    perm, sorted_keys = counting_sort(tp(keys.astype(dt)), bits, with_keys=True)
    want = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(np.array(perm), want)
    np.testing.assert_array_equal(np.array(sorted_keys).astype(np.uint64), keys[want])
