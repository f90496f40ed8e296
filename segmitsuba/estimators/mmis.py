"""Recursive marginal-MIS estimation over a pool of segments (shared/design/segment-transport.md §3).

For every query segment ``s`` whose end ``y_s`` has a non-delta BSDF:

    L̂(s) = T_s · ( Le(s) + Σ_{s' : |x' - y_s| < r} K f_r(s, s') L̂(s') / D(s') + private children )

``D(s')`` is the balance denominator: the densities of *every* sampled technique that could have produced
``s'`` — camera segments ending within ``r`` of ``x'`` (BSDF sampling at their end), light segments starting
within ``r`` of ``y'`` (adjoint BSDF sampling, converted to the ``(x', ω')`` measure by ``cos_x'/cos_y'``) and
the emission technique (``N_e`` light sub-paths). Each technique carries its Russian-roulette survival
probability, including techniques whose child was killed. ``D`` and the edge weights do not depend on
``L̂``: they are computed once per pass, and the recursion is solved by ``iterations`` sparse
matrix-vector products. Delta emitters' segments can come from the emission technique only, so their
``D`` is that term alone (its delta factors cancel against the emitted weight).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..grid import ClusterGrid, RadiusGrid, counting_sort, random_offset
from ..population import CAMERA, INVALID, LIGHT, SegmentPool, Surface, _gather


def _cluster_lists(cid: mi.UInt32, active: mi.Bool, clusters: int) -> tuple[mi.UInt32, mi.UInt32]:
    """Members grouped by cluster: ``(offsets[C + 1], member indices)`` (counting sort, stable)."""
    key = dr.select(active & (cid != INVALID), cid, clusters)
    counts = dr.zeros(mi.UInt32, clusters + 1)
    dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), key, mode=dr.ReduceMode.Local)
    offsets = dr.prefix_sum(counts)
    order = counting_sort(key, max(clusters, 1).bit_length())
    dr.eval(offsets, order)
    return offsets, order


class _ClusterKernel:
    """The cluster kernel (design §5): jittered voxels × normal bins over every segment end of the pass;
    two ends interact when they share a cluster, with ``K = 1 / A(C)``."""

    def __init__(self, pool: SegmentPool, h: float, seed: int, x_ok: mi.Bool, y_ok: mi.Bool):
        n = pool.size
        points = mi.Point3f(*[dr.concat([pool.x[i], pool.y[i]]) for i in range(3)])
        normals = mi.Vector3f(*[dr.concat([pool.nx[i], pool.ny[i]]) for i in range(3)])
        active = dr.concat([x_ok, y_ok])
        self.grid = ClusterGrid(points, normals, h, random_offset(h, seed), active=active)
        cid = self.grid.cluster_id
        self.cid_x = dr.gather(mi.UInt32, cid, dr.arange(mi.UInt32, n))
        self.cid_y = dr.gather(mi.UInt32, cid, dr.arange(mi.UInt32, n) + n)
        self.clusters = self.grid.num_clusters
        self.inv_area = dr.rcp(dr.maximum(self.grid.area, 1e-30)) if self.clusters else dr.zeros(mi.Float, 0)
        dr.eval(self.cid_x, self.cid_y, self.inv_area)

    def kernel_of(self, cid: mi.UInt32, active: mi.Bool) -> mi.Float:
        ok = active & (cid != INVALID)
        return dr.select(ok, dr.gather(mi.Float, self.inv_area, cid, ok), 0)

    def reduce(self, lists, row_cid: mi.UInt32, body, state, active: mi.Bool):
        """``state = body(state, j)`` for every listed member ``j`` of each row's cluster."""
        offsets, order = lists
        ok = active & (row_cid != INVALID)
        begin = dr.gather(mi.UInt32, offsets, row_cid, ok)
        end = dr.gather(mi.UInt32, offsets, row_cid + 1, ok)

        def step(i, st):
            return i + 1, body(st, dr.gather(mi.UInt32, order, i))

        _, state = dr.while_loop((begin, state), lambda i, st: ok & (i < end), step, label="cluster members")
        return state


@dataclass
class MMISSystem:
    """The linear system of one pass: edges (CSR by query segment) with their weights."""

    offsets: mi.UInt32
    cols: mi.UInt32
    weights: mi.Spectrum
    denominator: mi.Float
    gatherable: mi.Bool
    query: mi.Bool
    kernel: mi.Float  #: K of each query's kernel domain (1/(π r²), or 1/A(C) of its cluster)

    @property
    def edge_count(self) -> int:
        return dr.width(self.cols)


class MMISEstimator:
    def __init__(self, scene: mi.Scene, radius: float, light_paths: int, kernel: str = "radius", seed: int = 0):
        """``radius``: the disc radius of the radius kernel, or the voxel side of the cluster kernel."""
        self.scene = scene
        self.radius = float(radius)
        self.kernel_type = kernel
        self.seed = seed
        self.kernel = 1.0 / (dr.pi * self.radius**2)
        self.light_paths = light_paths
        self.ctx_radiance = mi.BSDFContext(mi.TransportMode.Radiance)
        self.ctx_importance = mi.BSDFContext(mi.TransportMode.Importance)

    # -- the system ---------------------------------------------------------------------------------------

    def build(self, pool: SegmentPool) -> MMISSystem:
        n = pool.size
        x_surf = pool.end_surface("x", dr.arange(mi.UInt32, n), dr.full(mi.Bool, True, n))
        y_surf = pool.end_surface("y", dr.arange(mi.UInt32, n), dr.full(mi.Bool, True, n))
        gatherable = (pool.x_surf != INVALID) & x_surf.smooth & ~pool.private & ~pool.delta_emit
        # a delta-emitter segment is gathered too, but no other technique can produce it
        gatherable_any = (pool.x_surf != INVALID) & x_surf.smooth & ~pool.private
        query = (pool.y_surf != INVALID) & y_surf.smooth
        arrival_smooth = pool.surf.smooth
        cam_tech = (pool.kind == CAMERA) & pool.attempt & arrival_smooth
        light_tech = (pool.kind == LIGHT) & pool.attempt & arrival_smooth
        y_known = (pool.kind == LIGHT) | (pool.y_surf != INVALID)

        cos_x = dr.abs(dr.dot(pool.nx, pool.wx))
        cos_y = dr.abs(dr.dot(pool.ny, pool.dy))
        dr.eval(gatherable, gatherable_any, query, cam_tech, light_tech, cos_x, cos_y)

        if self.kernel_type == "cluster":
            return self._build_cluster(pool, gatherable, gatherable_any, query, cam_tech, light_tech, y_known,
                                       cos_x, cos_y)
        denom = dr.zeros(mi.Float, n)
        if dr.any(cam_tech):
            grid = RadiusGrid(pool.y, self.radius, active=cam_tech)
            body = self._density_body(pool, pool.dy, pool.wx, self.ctx_radiance)
            denom += self._reduce_radius(grid, pool.x, body, gatherable)
        if dr.any(light_tech):
            grid = RadiusGrid(pool.x, self.radius, active=light_tech)
            body = self._density_body(pool, pool.wx, pool.dy, self.ctx_importance)
            light = self._reduce_radius(grid, pool.y, body, gatherable & y_known)
            denom += light * cos_x / dr.maximum(cos_y, 1e-8)
        denom = denom * self.kernel + self.light_paths * pool.emit_factor * cos_x
        denom = dr.select(pool.delta_emit, self.light_paths * cos_x, denom)
        dr.eval(denom)

        grid = RadiusGrid(pool.x, self.radius, active=gatherable_any & (denom > 0))
        offsets, cols = grid.neighbors(pool.y, active=query)
        weights = self._edge_weights(pool, offsets, cols, denom, query, dr.opaque(mi.Float, self.kernel))
        return MMISSystem(offsets=offsets, cols=cols, weights=weights, denominator=denom,
                          gatherable=gatherable_any, query=query, kernel=dr.full(mi.Float, self.kernel, n))

    def _density_body(self, pool: SegmentPool, tech_wi, query_wo, ctx: mi.BSDFContext):
        """Loop body adding ``q_t pdf_t(query_wo)`` of technique ``j``, whose BSDF lives on its walk-arrival
        surface (``pool.surf``), seen from ``tech_wi``."""
        surf, q = pool.surf, pool.q

        def body(state, j):
            s = _gather(Surface, surf, j)
            si = s.interaction(dr.gather(mi.Vector3f, tech_wi, j))
            pdf = si.bsdf().pdf(ctx, si, si.to_local(query_wo))
            return state + dr.gather(mi.Float, q, j) * pdf

        return body

    def _reduce_radius(self, grid: RadiusGrid, query_points, body, active: mi.Bool) -> mi.Float:
        total = grid.reduce(query_points, lambda st, j, pj, d2: body(st, j), dr.zeros(mi.Float, dr.width(active)),
                            active=active)
        dr.eval(total)
        return total

    def _build_cluster(self, pool, gatherable, gatherable_any, query, cam_tech, light_tech, y_known, cos_x, cos_y):
        n = pool.size
        x_ok = pool.x_surf != INVALID
        ck = _ClusterKernel(pool, self.radius, self.seed, x_ok, y_known)  # y of emission segments: on the emitter
        C = ck.clusters
        denom = dr.zeros(mi.Float, n)
        if dr.any(cam_tech):
            lists = _cluster_lists(ck.cid_y, cam_tech, C)
            body = self._density_body(pool, pool.dy, pool.wx, self.ctx_radiance)
            cam = ck.reduce(lists, ck.cid_x, body, dr.zeros(mi.Float, n), gatherable)
            denom += cam * ck.kernel_of(ck.cid_x, gatherable)
        if dr.any(light_tech):
            lists = _cluster_lists(ck.cid_x, light_tech, C)
            body = self._density_body(pool, pool.wx, pool.dy, self.ctx_importance)
            light = ck.reduce(lists, ck.cid_y, body, dr.zeros(mi.Float, n), gatherable & y_known)
            denom += light * ck.kernel_of(ck.cid_y, gatherable & y_known) * cos_x / dr.maximum(cos_y, 1e-8)
        denom += self.light_paths * pool.emit_factor * cos_x
        denom = dr.select(pool.delta_emit, self.light_paths * cos_x, denom)
        dr.eval(denom)

        # Edges: every gatherable segment starting in the cluster of the query's end.
        members_off, members = _cluster_lists(ck.cid_x, gatherable_any & (denom > 0), C)
        q_ok = query & (ck.cid_y != INVALID)
        c = dr.select(q_ok, ck.cid_y, 0)
        counts = dr.select(q_ok, dr.gather(mi.UInt32, members_off, c + 1) - dr.gather(mi.UInt32, members_off, c), 0)
        offsets = dr.prefix_sum(dr.concat([counts, mi.UInt32(0)]))
        total = int(dr.gather(mi.UInt32, offsets, mi.UInt32(n))[0]) if n else 0
        cols = dr.zeros(mi.UInt32, total)
        if total:
            start = dr.gather(mi.UInt32, members_off, c)
            out = dr.gather(mi.UInt32, offsets, dr.arange(mi.UInt32, n))

            def step(k):
                j = dr.gather(mi.UInt32, members, start + k)
                dr.scatter(cols, j, out + k)
                return (k + 1,)

            dr.while_loop((dr.zeros(mi.UInt32, n),), lambda k: q_ok & (k < counts), step, label="cluster edges")
            dr.eval(cols)
        kernel = ck.kernel_of(ck.cid_y, q_ok)
        weights = self._edge_weights(pool, offsets, cols, denom, q_ok, kernel)
        return MMISSystem(offsets=offsets, cols=cols, weights=weights, denominator=denom,
                          gatherable=gatherable_any, query=q_ok, kernel=kernel)

    def _edge_weights(self, pool: SegmentPool, offsets, cols, denom, query, kernel) -> mi.Spectrum:
        """``K f_r(s, s') / D(s')`` for every edge, with f_r the BSDF at ``y_s`` (cosine included)."""
        n = pool.size
        weights = dr.zeros(mi.Spectrum, dr.width(cols))
        if dr.width(cols) == 0:
            return weights
        ys = pool.end_surface("y", dr.arange(mi.UInt32, n), query)
        si = ys.interaction(pool.dy)
        bsdf = si.bsdf()
        begin = dr.gather(mi.UInt32, offsets, dr.arange(mi.UInt32, n))
        end = dr.gather(mi.UInt32, offsets, dr.arange(mi.UInt32, n) + 1)

        def cond(i):
            return query & (i < end)

        def step(i):
            j = dr.gather(mi.UInt32, cols, i)
            wo = dr.gather(mi.Vector3f, pool.wx, j)
            f = bsdf.eval(self.ctx_radiance, si, si.to_local(wo))
            w = f * kernel / dr.gather(mi.Float, denom, j)
            dr.scatter(weights, w, i)
            return (i + 1,)

        dr.while_loop((begin,), cond, step, label="MMIS edge weights")
        dr.eval(weights)
        return weights

    # -- the solve ----------------------------------------------------------------------------------------

    def solve(self, pool: SegmentPool, system: MMISSystem, iterations: int, emitted: mi.Spectrum) -> mi.Spectrum:
        """Iterate ``L̂ = T (Le + A L̂ + private)`` ``iterations`` times from ``L̂ = T Le``."""
        n = pool.size
        base = pool.chain * emitted
        radiance = mi.Spectrum(base)
        dr.eval(radiance)
        begin = dr.gather(mi.UInt32, system.offsets, dr.arange(mi.UInt32, n))
        end = dr.gather(mi.UInt32, system.offsets, dr.arange(mi.UInt32, n) + 1)
        # A camera segment that left a mixed vertex through its delta lobe feeds only its own parent (its
        # sequential continuation). Light-side private segments point the other way and feed nothing: the
        # camera side's private children cover delta lobes of mixed BSDFs.
        private = pool.private & (pool.parent != INVALID) & (pool.kind == CAMERA)
        has_private = dr.any(private)
        for _ in range(iterations):
            prev = radiance

            def step(i, acc, prev=prev):
                j = dr.gather(mi.UInt32, system.cols, i)
                acc += dr.gather(mi.Spectrum, system.weights, i) * dr.gather(mi.Spectrum, prev, j)
                return i + 1, acc

            if system.edge_count:
                _, gathered = dr.while_loop((begin, dr.zeros(mi.Spectrum, n)),
                                            lambda i, acc: system.query & (i < end), step, label="MMIS gather")
            else:
                gathered = dr.zeros(mi.Spectrum, n)
            if has_private:
                dr.scatter_reduce(dr.ReduceOp.Add, gathered, pool.lead * prev, pool.parent, private)
            radiance = base + pool.chain * gathered
            dr.eval(radiance)
        return radiance
