"""Direct light at the sharp vertices of a pool, sampled as ``path`` samples it (docs/maths.md §4.7).

A *sharp* camera segment reaches its end ``y`` from the sensor through delta lobes only (``y`` is what a
pixel sees, directly or in a mirror). There, the light that arrives along one straight ray from an emitter
(*covered* emission) gets an emitter sample, next-event estimation, that is not filtered. With ``sampled``
it and the walk's own BSDF sample take the place of the gathered covered emission, combined by the balance
heuristic as in ``path``; with ``mis`` it is combined with the gathered covered emission instead. The filter
still gathers everything else at ``y``: light scattered at least once, and emission through delta chains
such as caustics. Shadow edges and small highlights on what the camera sees are then not blurred by the
kernel, and direct light is no longer carried by noisy photons.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..population import CAMERA, INVALID, SegmentPool, emission_density
from .mmis import REDUCE, MMISSystem


@dataclass
class DirectLight:
    rows: mi.Bool  #: sharp segments whose end gets the sampled direct light
    value: mi.Spectrum  #: that light, leaving ``y`` toward ``x`` (before the segment's own chain)
    covered: mi.Float  #: per segment: the share of its emission that the rows no longer gather


def _interaction(p: mi.Point3f, n: mi.Normal3f, time: mi.Float, wavelengths) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f, dr.width(p))
    it.p, it.n, it.time = p, n, time
    if wavelengths is not None:
        it.wavelengths = wavelengths
    return it


def _emitter_sample(pool: SegmentPool, surf) -> mi.DirectionSample3f:
    """The light-side end of every segment as an emitter sample seen from its start ``x``."""
    ds = dr.zeros(mi.DirectionSample3f, pool.size)
    ds.p, ds.n, ds.uv, ds.time = pool.y, pool.ny, pool.emit_uv, surf.time
    ds.d = pool.wx
    ds.dist = dr.norm(pool.y - pool.x)
    ds.emitter = pool.emitter
    return ds


def sharp_direct_light(scene: mi.Scene, pool: SegmentPool, system: MMISSystem, max_depth: int, seed: int,
                       mis: bool = True) -> DirectLight:
    """Next-event estimation at the end of every sharp camera segment.

    ``mis``: combined by the balance heuristic with what the row gathers (its next-event density enters the
    denominator of the emission it gathers; the sample's own weight uses the denominator ``D`` that a gathered
    segment along it would have). Otherwise the sample replaces the gathered straight emission, and only the
    walk's own BSDF sample from the row is combined with it."""
    n = pool.size
    surf = pool.surf  # a camera segment's own record holds its end y
    rows = ((pool.kind == CAMERA) & pool.sharp & (pool.y_surf != INVALID) & surf.smooth
            & (pool.depth + 1 < max_depth))
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    value = dr.zeros(mi.Spectrum, n)
    covered = dr.zeros(mi.Float, n)
    if not dr.any(rows) or len(scene.emitters()) == 0:
        return DirectLight(rows=rows, value=value, covered=covered)

    si = surf.interaction(pool.dy)
    bsdf = si.bsdf()
    # opaque: a literal seed would compile the pass's kernels anew for every pool
    state = ((seed & 0xFFFFFFFF) * 0x9E3779B97F4A7C15 + 0x2545F491) & 0xFFFFFFFFFFFFFFFF
    # one stream per (camera sample, segment index): the same numbers whatever slot the segment took
    stream = (mi.UInt64(pool.index) << 32) | mi.UInt64(pool.pixel)
    rng = mi.PCG32()  # seed(), not the constructor: that one adds the lane index to the stream
    rng.seed(dr.opaque(mi.UInt64, state), stream)
    sample = mi.Point2f(rng.next_float32(), rng.next_float32())
    ds, em_weight = scene.sample_emitter_direction(si, sample, True, rows)
    sampled = rows & (ds.pdf > 0)
    f, pdf_bsdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), sampled)
    emissive = dr.any(mi.unpolarized_spectrum(pool.le) != 0)
    # Straight segments carrying emission from their y: what next-event estimation also samples.
    straight_emission = pool.straight & emissive & (pool.x_surf != INVALID)
    # every segment's start x, and its light-side end as an emitter sample seen from there
    x_it = _interaction(pool.x, pool.nx, surf.time, surf.wavelengths)
    ends = _emitter_sample(pool, surf)

    if mis:
        # K p_ne against the D of the gathered segment with this direction (docs/maths.md §4.7)
        it = _interaction(si.p, si.n, si.time, surf.wavelengths)
        infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
        smooth_light = sampled & ~ds.delta
        d_ne = system.segment_density(smooth_light, ds.d, ds.p, ds.n, ~infinite,
                                      emission_density(scene, ds, it, smooth_light))
        k_pdf = system.kernel * ds.pdf
        w_nee = dr.select(ds.delta, 1.0, k_pdf / dr.maximum(k_pdf + d_ne, 1e-30))
        # what each gathered straight emission loses to it: K p_ne / (D + K p_ne), with p_ne seen from its x
        smooth_src = straight_emission & ~pool.delta_emit
        k_src = system.source_kernel * scene.pdf_emitter_direction(x_it, ends, smooth_src)
        covered = dr.select(smooth_src, k_src / dr.maximum(system.denominator + k_src, 1e-30), 0)
        covered = dr.select(straight_emission & pool.delta_emit, 1.0, covered)
    else:
        # the BSDF technique exists where the walk tried to continue, with its survival probability
        p_b = dr.select(pool.attempt, pool.q * pdf_bsdf, 0)
        w_nee = dr.select(ds.delta, 1.0, ds.pdf / dr.maximum(ds.pdf + p_b, 1e-30))
        # the walk's own BSDF sample from a row: a straight, non-private child ending on an emitter
        parent = pool.parent
        child = (pool.kind == CAMERA) & (parent != INVALID) & ~pool.private & pool.straight & emissive
        child &= dr.gather(mi.Bool, rows, parent, child)
        pdf_nee = scene.pdf_emitter_direction(x_it, ends, child)
        p_c = dr.gather(mi.Float, pool.q, parent, child) * pool.pdf
        w_bsdf = p_c / dr.maximum(p_c + pdf_nee, 1e-30)
        dr.scatter_reduce(dr.ReduceOp.Add, value, pool.lead * pool.chain * pool.le * w_bsdf, parent, child,
                          mode=REDUCE)
        covered = dr.select(straight_emission, 1.0, 0.0)
    value += dr.select(sampled, f * em_weight * w_nee, 0)
    dr.eval(rows, value, covered)
    return DirectLight(rows=rows, value=value, covered=covered)
