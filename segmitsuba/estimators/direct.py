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

from ..population import CAMERA, INVALID, SegmentPool, _gather, emission_density
from .mmis import REDUCE, MMISSystem


@dataclass
class DirectLight:
    rows: mi.Bool  #: sharp segments whose end gets the sampled direct light
    value: mi.Spectrum  #: that light, leaving ``y`` toward ``x`` (before the segment's own chain)
    covered: mi.Float  #: per segment: the share of its emission that the rows no longer gather
    #: light of delta emitters sampled at the other camera queries, where no technique of the pool reaches it
    #: (filters without light sub-paths); added to what they gather, or None
    delta: mi.Spectrum | None = None


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
                       mis: bool = True, samples: int = 1, delta_everywhere: bool = False) -> DirectLight:
    """Next-event estimation at the end of every sharp camera segment, ``samples`` emitter samples per row.

    ``mis``: combined by the balance heuristic with what the row gathers (its next-event density enters the
    denominator of the emission it gathers; the sample's own weight uses the denominator ``D`` that a gathered
    segment along it would have). Otherwise the samples replace the gathered straight emission, and are
    combined with the walk's own BSDF sample from the row and ``samples - 1`` more BSDF samples there
    (docs/maths.md §4.7).

    ``delta_everywhere`` (pools without light sub-paths): every other camera query with a smooth BSDF also
    gets ``samples`` emitter samples, of which only those of delta lights count: nothing else in such a pool
    carries a delta light's light past what the camera sees."""
    n = pool.size
    surf = pool.surf  # a camera segment's own record holds its end y
    # camera queries where the walk may still add a segment; the sharp ones are the rows
    queries = (pool.kind == CAMERA) & (pool.y_surf != INVALID) & surf.smooth & (pool.depth + 1 < max_depth)
    rows = queries & pool.sharp
    value = dr.zeros(mi.Spectrum, n)
    covered = dr.zeros(mi.Float, n)
    emitters = scene.emitters()
    if not dr.any(rows) or len(emitters) == 0:
        return DirectLight(rows=rows, value=value, covered=covered)

    # Pay only for samples that can differ: the one emitter sample of a lone delta light is exact, and BSDF
    # samples never reach a delta light.
    delta = [mi.has_flag(e.flags(), mi.EmitterFlags.Delta) for e in emitters]
    emitter_samples = 1 if len(emitters) == 1 and delta[0] else samples
    bsdf_samples = 0 if all(delta) else samples - 1
    m = float(emitter_samples)
    # the BSDF technique of the walk's own child exists where the walk tried to continue, with its survival
    # probability; the extra BSDF samples always exist
    q_child = dr.select(pool.attempt, pool.q, 0.0)
    emissive = dr.any(mi.unpolarized_spectrum(pool.le) != 0)
    # Straight segments carrying emission from their y: what next-event estimation also samples.
    straight_emission = pool.straight & emissive & (pool.x_surf != INVALID)
    # every segment's start x, and its light-side end as an emitter sample seen from there
    x_it = _interaction(pool.x, pool.nx, surf.time, surf.wavelengths)
    ends = _emitter_sample(pool, surf)

    if mis:
        # K p_ne against D of the gathered segment along each sample, over the whole pool (the lanes of
        # segment_density)
        si = surf.interaction(pool.dy)
        value = _nee_against_gather(scene, system, si, _row_rng(pool, seed, None), emitter_samples, rows)
        # what each gathered straight emission loses to the samples: m K p_ne / (D + m K p_ne), p_ne from its x
        smooth_src = straight_emission & ~pool.delta_emit
        k_src = m * system.source_kernel * scene.pdf_emitter_direction(x_it, ends, smooth_src)
        covered = dr.select(smooth_src, k_src / dr.maximum(system.denominator + k_src, 1e-30), 0)
        covered = dr.select(straight_emission & pool.delta_emit, 1.0, covered)
    else:
        # the samples run over the rows only
        row, si = _compressed(pool, rows)
        nee = _nee_with_bsdf(scene, si, _row_rng(pool, seed, row), emitter_samples, bsdf_samples,
                             dr.gather(mi.Float, q_child, row))
        dr.scatter_reduce(dr.ReduceOp.Add, value, nee, row, mode=REDUCE)
        # the walk's own BSDF sample from a row: a straight, non-private child ending on an emitter
        parent = pool.parent
        child = (pool.kind == CAMERA) & (parent != INVALID) & ~pool.private & pool.straight & emissive
        child &= dr.gather(mi.Bool, rows, parent, child)
        pdf_nee = scene.pdf_emitter_direction(x_it, ends, child)
        p_c = dr.gather(mi.Float, q_child, parent, child) * pool.pdf
        w_bsdf = p_c / dr.maximum(p_c + bsdf_samples * pool.pdf + m * pdf_nee, 1e-30)
        dr.scatter_reduce(dr.ReduceOp.Add, value, pool.lead * pool.chain * pool.le * w_bsdf, parent, child,
                          mode=REDUCE)
        covered = dr.select(straight_emission, 1.0, 0.0)
    delta_light = None
    if delta_everywhere and any(delta):
        others = queries & ~pool.sharp
        if dr.any(others):
            row, si = _compressed(pool, others)
            delta_light = dr.zeros(mi.Spectrum, n)
            dr.scatter_reduce(dr.ReduceOp.Add, delta_light,
                              _nee_delta_only(scene, si, _row_rng(pool, seed, row), emitter_samples), row,
                              mode=REDUCE)
            dr.eval(delta_light)
    dr.eval(rows, value, covered)
    return DirectLight(rows=rows, value=value, covered=covered, delta=delta_light)


def _compressed(pool: SegmentPool, mask: mi.Bool) -> tuple[mi.UInt32, mi.SurfaceInteraction3f]:
    """The segments in ``mask`` and the interactions at their ends ``y``, seen from their starts."""
    row = dr.compress(mask)
    return row, _gather(pool.surf, row).interaction(dr.gather(mi.Vector3f, pool.dy, row))


def _row_rng(pool: SegmentPool, seed: int, row: mi.UInt32 | None) -> mi.PCG32:
    """Random numbers of the rows ``row`` (all segments if None), one stream per (camera sample, segment
    index): the same numbers whatever slot a segment took in the pool."""
    index, pixel = pool.index, pool.pixel
    if row is not None:
        index, pixel = dr.gather(mi.UInt32, index, row), dr.gather(mi.UInt32, pixel, row)
    # opaque: a literal seed would compile the pass's kernels anew for every pool
    state = ((seed & 0xFFFFFFFF) * 0x9E3779B97F4A7C15 + 0x2545F491) & 0xFFFFFFFFFFFFFFFF
    rng = mi.PCG32()  # seed(), not the constructor: that one adds the lane index to the stream
    rng.seed(dr.opaque(mi.UInt64, state), (mi.UInt64(index) << 32) | mi.UInt64(pixel))
    return rng


def _emitter_term(scene: mi.Scene, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, sample: mi.Point2f,
                  active: mi.Bool):
    """One emitter sample from ``si``: its BSDF-weighted emission f Le / p_e, its density and the BSDF's."""
    ds, em_weight = scene.sample_emitter_direction(si, sample, True, active)
    sampled = active & (ds.pdf > 0)
    f, pdf_bsdf = bsdf.eval_pdf(mi.BSDFContext(mi.TransportMode.Radiance), si, si.to_local(ds.d), sampled)
    return ds, dr.select(sampled, f * em_weight, 0), pdf_bsdf


@dr.syntax
def _nee_with_bsdf(scene: mi.Scene, si: mi.SurfaceInteraction3f, rng: mi.PCG32, emitter_samples: int,
                   bsdf_samples: int, q_child: mi.Float) -> mi.Spectrum:
    """``emitter_samples`` emitter samples and ``bsdf_samples`` BSDF samples from each row, balance heuristic
    with sample counts over the emitter technique (density p_e), the walk's child (one sample of density q p_b)
    and the extra BSDF samples (density p_b): every sample counts f Le / (m_e p_e + (q + m_b) p_b)."""
    bsdf = si.bsdf()
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    m_e = dr.opaque(mi.Float, emitter_samples)
    m_b = dr.opaque(mi.UInt32, bsdf_samples)
    q_b = q_child + mi.Float(m_b)
    value = dr.zeros(mi.Spectrum, dr.width(si.p))
    j = mi.UInt32(0)
    while j < dr.opaque(mi.UInt32, emitter_samples):
        ds, fle, pdf_b = _emitter_term(scene, si, bsdf, mi.Point2f(rng.next_float32(), rng.next_float32()),
                                       True)
        w = dr.select(ds.delta, 1 / m_e, ds.pdf / dr.maximum(m_e * ds.pdf + q_b * pdf_b, 1e-30))
        value += fle * w
        # the first emitter sample's BSDF partner is the walk's own child
        extra = (j > 0) & (j <= m_b)
        u = rng.next_float32()
        bs, bsdf_weight = bsdf.sample(ctx, si, u, mi.Point2f(rng.next_float32(), rng.next_float32()), extra)
        extra &= (bs.pdf > 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        hit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), extra)
        emitter = hit.emitter(scene, extra)
        extra &= emitter != None  # noqa: E711 (Dr.Jit pointer test)
        le = emitter.eval(hit, extra)
        ds_hit = mi.DirectionSample3f(scene, hit, si)
        smooth = extra & ~mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
        p_e = scene.pdf_emitter_direction(si, ds_hit, smooth)
        w_b = bs.pdf / dr.maximum(m_e * p_e + q_b * bs.pdf, 1e-30)
        value += dr.select(extra, bsdf_weight * le * w_b, 0)
        j += 1
    return value


@dr.syntax
def _nee_delta_only(scene: mi.Scene, si: mi.SurfaceInteraction3f, rng: mi.PCG32, samples: int) -> mi.Spectrum:
    """``samples`` emitter samples from each query, counting those that chose a delta light (each f Le / (m p)):
    an unbiased estimate of the delta lights' direct light alone."""
    bsdf = si.bsdf()
    m = dr.opaque(mi.Float, samples)
    value = dr.zeros(mi.Spectrum, dr.width(si.p))
    j = mi.UInt32(0)
    while j < dr.opaque(mi.UInt32, samples):
        ds, fle, _ = _emitter_term(scene, si, bsdf, mi.Point2f(rng.next_float32(), rng.next_float32()), True)
        value += dr.select(ds.delta, fle / m, 0)
        j += 1
    return value


def _nee_against_gather(scene: mi.Scene, system: MMISSystem, si: mi.SurfaceInteraction3f, rng: mi.PCG32,
                        samples: int, rows: mi.Bool) -> mi.Spectrum:
    """``samples`` emitter samples from each row, each weighted K p_e / (m K p_e + D(s_e)) against the gathered
    segment s_e along it (docs/maths.md §4.7). A loop in Python: ``segment_density`` runs its own loops over
    the pool's grid."""
    bsdf = si.bsdf()
    it = _interaction(si.p, si.n, si.time, si.wavelengths if mi.is_spectral else None)
    value = dr.zeros(mi.Spectrum, dr.width(si.p))
    for _ in range(samples):
        ds, fle, _ = _emitter_term(scene, si, bsdf, mi.Point2f(rng.next_float32(), rng.next_float32()), rows)
        infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
        smooth_light = rows & (ds.pdf > 0) & ~ds.delta
        d_ne = system.segment_density(smooth_light, ds.d, ds.p, ds.n, ~infinite,
                                      emission_density(scene, ds, it, smooth_light))
        k_pdf = system.kernel * ds.pdf
        value += fle * dr.select(ds.delta, 1 / samples, k_pdf / dr.maximum(samples * k_pdf + d_ne, 1e-30))
        dr.eval(value, rng)
    return value
