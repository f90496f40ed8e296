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

from ..grid import RadiusGrid
from ..population import CAMERA, INVALID, LIGHT, SegmentPool, Surface, _gather


@dataclass
class MMISSystem:
    """The linear system of one pass: edges (CSR by query segment) with their weights."""

    offsets: mi.UInt32
    cols: mi.UInt32
    weights: mi.Spectrum
    denominator: mi.Float
    gatherable: mi.Bool
    query: mi.Bool

    @property
    def edge_count(self) -> int:
        return dr.width(self.cols)


class MMISEstimator:
    def __init__(self, scene: mi.Scene, radius: float, light_paths: int, timings: dict | None = None):
        self.scene = scene
        self.radius = float(radius)
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

        denom = dr.zeros(mi.Float, n)
        if dr.any(cam_tech):
            denom += self._technique_sum(pool, cam_tech, pool.y, pool.x, pool.dy, pool.wx, gatherable,
                                         self.ctx_radiance)
        if dr.any(light_tech):
            light = self._technique_sum(pool, light_tech, pool.x, pool.y, pool.wx, pool.dy,
                                        gatherable & y_known, self.ctx_importance)
            denom += light * cos_x / dr.maximum(cos_y, 1e-8)
        denom = denom * self.kernel + self.light_paths * pool.emit_factor * cos_x
        denom = dr.select(pool.delta_emit, self.light_paths * cos_x, denom)
        dr.eval(denom)

        grid = RadiusGrid(pool.x, self.radius, active=gatherable_any & (denom > 0))
        offsets, cols = grid.neighbors(pool.y, active=query)
        weights = self._edge_weights(pool, offsets, cols, denom, query)
        return MMISSystem(offsets=offsets, cols=cols, weights=weights, denominator=denom,
                          gatherable=gatherable_any, query=query)

    def _technique_sum(self, pool: SegmentPool, techniques: mi.Bool, tech_points, query_points, tech_wi,
                       query_wo, active: mi.Bool, ctx: mi.BSDFContext) -> mi.Float:
        """Σ_t q_t pdf_t(query_wo) over techniques t within the radius of each query point.

        A technique's BSDF lives on its walk-arrival surface (``pool.surf``), seen from ``tech_wi``."""
        grid = RadiusGrid(tech_points, self.radius, active=techniques)
        surf, q = pool.surf, pool.q

        def body(state, j, pj, d2):
            s = _gather(Surface, surf, j)
            wi = dr.gather(mi.Vector3f, tech_wi, j)
            si = s.interaction(wi)
            pdf = si.bsdf().pdf(ctx, si, si.to_local(query_wo))
            return state + dr.gather(mi.Float, q, j) * pdf

        total = grid.reduce(query_points, body, dr.zeros(mi.Float, pool.size), active=active)
        dr.eval(total)
        return total

    def _edge_weights(self, pool: SegmentPool, offsets, cols, denom, query) -> mi.Spectrum:
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
        kernel = dr.opaque(mi.Float, self.kernel)

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
        has_private = dr.any(pool.private & (pool.parent != INVALID))
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
                child = pool.private & (pool.parent != INVALID)
                dr.scatter_reduce(dr.ReduceOp.Add, gathered, pool.lead * prev, pool.parent, child)
            radiance = base + pool.chain * gathered
            dr.eval(radiance)
        return radiance
