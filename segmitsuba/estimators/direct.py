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

from ..population import CAMERA, INVALID, SegmentPool, emission_density, emitter_sample_of, point_interaction
from .mmis import REDUCE, MMISSystem


@dataclass
class FinalGather:
    """The extra BSDF samples of sharp glossy rows that gather the pool where they land (docs/maths.md §4.9):
    one lane per sample that reached a Lambertian receiver gathered through its cluster's ``V_C``."""

    row: mi.UInt32  #: the row (pool segment) of each sample
    cluster: mi.UInt32  #: the cluster it landed in
    normal: mi.Vector3f  #: the receiver's oriented shading normal
    factor: mi.Spectrum  #: f/p / (q + m_b) of the sample times K ρ/π of the receiver
    #: per segment: the share of a private child's feed that its parent's final gathering leaves to it
    child_scale: mi.Float


@dataclass
class DirectLight:
    rows: mi.Bool  #: sharp segments whose end gets the sampled direct light
    value: mi.Spectrum  #: that light, leaving ``y`` toward ``x`` (before the segment's own chain)
    covered: mi.Float  #: per segment: the share of its emission that the rows no longer gather
    #: light of delta emitters sampled at the other camera queries, where no technique of the pool reaches it
    #: (filters without light sub-paths); added to what they gather, or None
    delta: mi.Spectrum | None = None
    #: private children of rows whose own emission ``value`` already holds (MIS-weighted): they feed their
    #: parent only what they gathered, or None
    counted: mi.Bool | None = None
    final: FinalGather | None = None


def sharp_direct_light(scene: mi.Scene, pool: SegmentPool, system: MMISSystem, max_depth: int, seed: int,
                       mis: bool = True, samples: int = 1, delta_everywhere: bool = False,
                       final_gather: bool = True, sharp_apart: bool = False) -> DirectLight:
    """Next-event estimation at the end of every sharp camera segment, ``samples`` emitter samples per row.

    With private glossy vertices (``system.glossy``: the camera walks continue privately from them, and they
    gather nothing, docs/maths.md §4.8), every camera query at a glossy vertex is a row too, with one emitter
    sample combined with the walk's own (private) child as ``path`` does; at the sharp ones, ``samples`` as
    elsewhere, and with ``final_gather`` their extra BSDF samples also gather the pool where they land
    (docs/maths.md §4.9).

    ``mis``: combined by the balance heuristic with what the row gathers (its next-event density enters the
    denominator of the emission it gathers; the sample's own weight uses the denominator ``D`` that a gathered
    segment along it would have). Otherwise the samples replace the gathered straight emission, and are
    combined with the walk's own BSDF sample from the row and ``samples - 1`` more BSDF samples there
    (docs/maths.md §4.7).

    ``sharp_apart``: the direct light at the sharp rows is estimated apart from the pool, by camera samples of
    their own (:func:`sharp_chain_light`, docs/maths.md §4.10): the sharp rows still gather no straight
    emission and their private children feed them no emission, but they take no emitter samples and their
    extra BSDF samples only gather (final gathering).

    ``delta_everywhere`` (pools without light sub-paths): every other camera query with a smooth BSDF also
    gets ``samples`` emitter samples, of which only those of delta lights count: nothing else in such a pool
    carries a delta light's light past what the camera sees."""
    n = pool.size
    surf = pool.surf  # a camera segment's own record holds its end y
    # camera queries where the walk may still add a segment; the sharp ones are the rows
    queries = (pool.kind == CAMERA) & (pool.y_surf != INVALID) & surf.smooth & (pool.depth + 1 < max_depth)
    glossy = queries & system.glossy if system.glossy is not None else dr.zeros(mi.Bool, n)
    rows = queries & (pool.sharp | glossy)
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
    x_it = point_interaction(pool.x, pool.nx, surf.time, surf.wavelengths)
    ends = emitter_sample_of(pool)

    # rows that gather nothing (glossy) combine their samples with their private child, never with a gather
    mis_rows = rows & ~glossy if mis else dr.zeros(mi.Bool, n)
    sampled_rows = rows & ~mis_rows
    counted = None
    if mis:
        # K p_ne against D of the gathered segment along each sample, over the whole pool (the lanes of
        # segment_density)
        si = surf.interaction(pool.dy)
        value = _nee_against_gather(scene, system, si, _row_rng(pool, seed, None), emitter_samples, mis_rows)
        # what each gathered straight emission loses to the samples: m K p_ne / (D + m K p_ne), p_ne from its x
        smooth_src = straight_emission & ~pool.delta_emit
        k_src = m * system.source_kernel * scene.pdf_emitter_direction(x_it, ends, smooth_src)
        covered = dr.select(smooth_src, k_src / dr.maximum(system.denominator + k_src, 1e-30), 0)
        covered = dr.select(straight_emission & pool.delta_emit, 1.0, covered)
    else:
        covered = dr.select(straight_emission, 1.0, 0.0)
    final = None
    if dr.any(sampled_rows):
        # the samples run over these rows only: at a sharp row `samples` emitter samples and `samples - 1` BSDF
        # samples besides the walk's own, at a glossy one one emitter sample
        m_e = dr.select(pool.sharp, dr.opaque(mi.Float, 0.0 if sharp_apart else m), 1.0)
        m_b = dr.select(pool.sharp, mi.UInt32(0 if sharp_apart else bsdf_samples), 0)
        # Sharp glossy rows gather nothing: their extra BSDF samples also gather the pool where they land
        # (final gathering, docs/maths.md §4.9), delta lights or not.
        slots = samples - 1 if system.receiver_cluster is not None and final_gather else 0
        gathering = sampled_rows & glossy & pool.sharp if slots else dr.zeros(mi.Bool, n)
        slots = slots if dr.any(gathering) else 0
        if slots:
            m_b = dr.select(gathering, mi.UInt32(slots), m_b)
        # apart: the sharp rows' direct light is not sampled here, only their final gathering
        emits = ~pool.sharp if sharp_apart else dr.full(mi.Bool, True, n)
        sampling = sampled_rows & (emits | gathering)
        record = None
        if dr.any(sampling):
            row, si = _compressed(pool, sampling)
            record = _FinalSamples(dr.width(row), slots, dr.gather(mi.Bool, gathering, row)) if slots else None
            nee = _nee_with_bsdf(scene, si, _row_rng(pool, seed, row), dr.gather(mi.Float, m_e, row),
                                 dr.gather(mi.UInt32, m_b, row), dr.gather(mi.Float, q_child, row), record,
                                 dr.gather(mi.Bool, emits, row))
            dr.scatter_reduce(dr.ReduceOp.Add, value, nee, row, mode=REDUCE)
        if record is not None:
            final = record.final(system, pool, row, gathering, q_child, m_b)
        # the walk's own BSDF sample from a row: a straight child ending on an emitter, not one that left the
        # row through a delta lobe (private, and a direction no emitter sample has)
        parent = pool.parent
        child = (pool.kind == CAMERA) & (parent != INVALID) & pool.straight & emissive
        child &= dr.gather(mi.Bool, sampled_rows, parent, child)
        child &= ~pool.private | dr.gather(mi.Bool, glossy, parent, child)
        pdf_nee = scene.pdf_emitter_direction(x_it, ends, child)
        p_c = dr.gather(mi.Float, q_child, parent, child) * pool.pdf
        w_bsdf = p_c / dr.maximum(p_c + mi.Float(dr.gather(mi.UInt32, m_b, parent, child)) * pool.pdf
                                  + dr.gather(mi.Float, m_e, parent, child) * pdf_nee, 1e-30)
        adds = child & dr.gather(mi.Bool, emits, parent, child)
        dr.scatter_reduce(dr.ReduceOp.Add, value, pool.lead * pool.chain * pool.le * w_bsdf, parent, adds,
                          mode=REDUCE)
        counted = child & pool.private
        dr.eval(counted)
    delta_light = None
    if delta_everywhere and any(delta):
        others = queries & ~rows
        if dr.any(others):
            row, si = _compressed(pool, others)
            delta_light = dr.zeros(mi.Spectrum, n)
            dr.scatter_reduce(dr.ReduceOp.Add, delta_light,
                              _nee_delta_only(scene, si, _row_rng(pool, seed, row), emitter_samples), row,
                              mode=REDUCE)
            dr.eval(delta_light)
    dr.eval(rows, value, covered)
    return DirectLight(rows=rows, value=value, covered=covered, delta=delta_light, counted=counted, final=final)


def _compressed(pool: SegmentPool, mask: mi.Bool) -> tuple[mi.UInt32, mi.SurfaceInteraction3f]:
    """The segments in ``mask`` and the interactions at their ends ``y``, seen from their starts."""
    row = dr.compress(mask)
    return row, pool.walk_surface(row).interaction(dr.gather(mi.Vector3f, pool.dy, row))


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


class _FinalSamples:
    """Where the extra BSDF samples of the final-gathering rows land: ``slots`` per row, written from inside the
    sampling loop (slot ``row · slots + j - 1``)."""

    def __init__(self, rows: int, slots: int, gathering: mi.Bool):
        size = rows * slots
        self.slots, self.gathering = slots, gathering
        self.p, self.n, self.normal = dr.zeros(mi.Point3f, size), dr.zeros(mi.Normal3f, size), dr.zeros(
            mi.Vector3f, size)
        self.weight = dr.zeros(mi.Spectrum, size)
        self.lambertian, self.unlit = dr.zeros(mi.Bool, size), dr.zeros(mi.Bool, size)

    def write(self, lane: mi.UInt32, j: mi.UInt32, hit: mi.SurfaceInteraction3f, weight: mi.Spectrum,
              active: mi.Bool) -> None:
        from .mmis import lambertian_at

        # not `&=`: that would change the caller's mask in place
        active = active & dr.gather(mi.Bool, self.gathering, lane, active) & hit.is_valid()
        lam, normal, scale = lambertian_at(hit, active)
        # ρ/π: the BSDF toward the oriented normal (cosine 1)
        albedo = hit.bsdf().eval(mi.BSDFContext(mi.TransportMode.Radiance), hit, hit.to_local(normal), lam)
        slot = lane * self.slots + j - 1
        for target, v in ((self.p, hit.p), (self.n, hit.n), (self.normal, normal), (self.weight, weight * albedo),
                          (self.lambertian, lam), (self.unlit, lam & (scale == 0))):
            dr.scatter(target, v, slot, active)

    def final(self, system: MMISSystem, pool: SegmentPool, row: mi.UInt32, gathering: mi.Bool, q_child: mi.Float,
              m_b: mi.UInt32) -> FinalGather:
        """The samples that landed on receivers gathered through ``V_C``, and the share left to the children."""
        dr.eval(self.p, self.n, self.normal, self.weight, self.lambertian, self.unlit)
        n = pool.size
        lp = system.lumped
        parent = pool.parent
        # The walk's own child of such a row covers the same directions where it lands on such a receiver
        # straight away (the band's receivers list edges: not these), with density q p_b of (q + m_b) p_b. Both
        # must see the same receivers: a cluster counts only if ends of other walks than the row's own are in
        # it (the child's end, and its own child's start there, would make it exist for the child alone).
        child = (pool.kind == CAMERA) & pool.private & (parent != INVALID) & pool.straight
        child &= dr.gather(mi.Bool, gathering, parent, child)
        cid = lp.cluster
        next_here = (parent != INVALID) & dr.gather(mi.Bool, child, parent, parent != INVALID) & (
            lp.start_cluster == dr.gather(mi.UInt32, cid, parent, parent != INVALID))
        own = dr.select(child, mi.UInt32(1), 0)
        dr.scatter_reduce(dr.ReduceOp.Add, own, mi.UInt32(1), parent, next_here, mode=REDUCE)
        child &= lp.query & ~lp.banded & (cid != INVALID)
        child &= dr.gather(mi.UInt32, lp.members, cid, child) > own
        # per row: its child's cluster and the ends its walk put there
        row_cluster = dr.full(mi.UInt32, INVALID, n)
        row_own = dr.zeros(mi.UInt32, n)
        seen = (pool.kind == CAMERA) & (parent != INVALID) & dr.gather(mi.Bool, gathering, parent, parent != INVALID)
        seen &= cid != INVALID
        dr.scatter(row_cluster, cid, parent, seen)
        dr.scatter(row_own, own, parent, seen)
        cluster, fits, kernel = system.receiver_cluster(self.p, self.n, self.normal, self.lambertian, self.unlit,
                                                        self.lambertian)
        dr.eval(cluster, fits, kernel)  # one lookup loop: each later evaluation would run it again
        slot_row = dr.gather(mi.UInt32, row, dr.arange(mi.UInt32, dr.width(self.p)) // dr.opaque(mi.UInt32,
                                                                                                  self.slots))
        mine = dr.gather(mi.UInt32, row_cluster, slot_row) == cluster
        others = dr.gather(mi.UInt32, lp.members, cluster, fits) - dr.select(
            mine, dr.gather(mi.UInt32, row_own, slot_row), 0)
        fits &= (others > 0) & dr.any(mi.unpolarized_spectrum(self.weight) != 0)  # black receivers add nothing
        keep = dr.compress(fits)
        slot_row = dr.gather(mi.UInt32, slot_row, keep)
        factor = dr.gather(mi.Spectrum, self.weight * kernel, keep)
        q = dr.gather(mi.Float, q_child, parent, child)
        scale = dr.select(child, q / dr.maximum(q + mi.Float(dr.gather(mi.UInt32, m_b, parent, child)), 1e-30),
                          1.0)
        out = FinalGather(row=slot_row, cluster=dr.gather(mi.UInt32, cluster, keep),
                          normal=dr.gather(mi.Vector3f, self.normal, keep), factor=factor, child_scale=scale)
        dr.eval(out.row, out.cluster, out.normal, out.factor, out.child_scale)
        return out


@dr.syntax
def _nee_with_bsdf(scene: mi.Scene, si: mi.SurfaceInteraction3f, rng: mi.PCG32, m_e: mi.Float,
                   m_b: mi.UInt32, q_child: mi.Float, record: _FinalSamples | None = None,
                   emits: mi.Bool | None = None) -> mi.Spectrum:
    """``m_e`` emitter samples and ``m_b`` BSDF samples from each row (per row), balance heuristic with sample
    counts over the emitter technique (density p_e), the walk's child (one sample of density q p_b) and the
    extra BSDF samples (density p_b): every sample counts f Le / (m_e p_e + (q + m_b) p_b). ``record``: where
    the BSDF samples land, with their weight f/p / (q + m_b), for final gathering. ``emits``: rows whose BSDF
    samples count the emission they reach (None: all)."""
    bsdf = si.bsdf()
    emits = dr.full(mi.Bool, True, dr.width(si.p)) if emits is None else emits
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    q_b = q_child + mi.Float(m_b)
    lane = dr.arange(mi.UInt32, dr.width(si.p))
    value = dr.zeros(mi.Spectrum, dr.width(si.p))
    # Two loops, so that a row pays for emitter samples only as many times as it takes them, and for BSDF samples
    # likewise (masked work in a loop still costs its lanes' packet: final-gathering rows take no emitter sample)
    j = mi.UInt32(0)
    while j < mi.UInt32(m_e):
        ds, fle, pdf_b = _emitter_term(scene, si, bsdf, mi.Point2f(rng.next_float32(), rng.next_float32()), True)
        w = dr.select(ds.delta, 1 / m_e, ds.pdf / dr.maximum(m_e * ds.pdf + q_b * pdf_b, 1e-30))
        value += fle * w
        j += 1
    # the first emitter sample's BSDF partner is the walk's own child: these are the extra ones, 1 .. m_b
    j = mi.UInt32(1)
    while j <= m_b:
        u = rng.next_float32()
        bs, bsdf_weight = bsdf.sample(ctx, si, u, mi.Point2f(rng.next_float32(), rng.next_float32()))
        extra = (bs.pdf > 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        hit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), extra)
        if record is not None:
            record.write(lane, j, hit, bsdf_weight / q_b, extra)
        extra &= emits
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
    it = point_interaction(si.p, si.n, si.time, si.wavelengths if mi.is_spectral else None)
    value = dr.zeros(mi.Spectrum, dr.width(si.p))
    for _ in range(samples):
        ds, fle, _ = _emitter_term(scene, si, bsdf, mi.Point2f(rng.next_float32(), rng.next_float32()), rows)
        infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
        smooth_light = rows & (ds.pdf > 0) & ~ds.delta
        d_ne = system.segment_density(smooth_light, ds.d, ds.p, ds.n, ~infinite,
                                      emission_density(scene, ds, it, smooth_light))
        k_pdf = system.kernel * ds.pdf
        weight = dr.select(smooth_light, k_pdf / dr.maximum(samples * k_pdf + d_ne, 1e-30), 0)
        value += dr.select(rows & ds.delta, fle / samples, dr.select(smooth_light, fle * weight, 0))
        dr.eval(value, rng)
    return value


def _power_heuristic(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    """The power heuristic (exponent 2) of one sample each of two techniques, as ``path`` weighs them."""
    r = pdf_b / dr.maximum(pdf_a, 1e-30)
    return dr.rcp(1.0 + r * r)  # r*r may be inf: weight 0


def emitter_samples_suffice(scene: mi.Scene) -> bool:
    """Whether an emitter sample alone serves a Lambertian vertex as well as one combined with a BSDF sample:
    every emitter is an area or a delta emitter. An environment (constant or map) is left to the BSDF sample too,
    which finds the sky where a cosine lobe looks and an emitter sample does not (docs/maths.md §4.10)."""
    flags = [e.flags() for e in scene.emitters()]
    infinite, delta = mi.EmitterFlags.Infinite, mi.EmitterFlags.Delta
    return not any(mi.has_flag(f, infinite) and not mi.has_flag(f, delta) for f in flags)


def only_delta_emitters(scene: mi.Scene) -> bool:
    """Every emitter of ``scene`` is a delta one (point, spot, directional, projector): no BSDF sample of a
    smooth lobe finds emission."""
    return all(mi.has_flag(e.flags(), mi.EmitterFlags.Delta) for e in scene.emitters())


def _emitter_sample_alone(flags: mi.UInt32, delta_only: bool, lambertian: bool) -> mi.Bool:
    """Where a vertex of :func:`sharp_chain_light` takes the emitter sample alone: under delta emitters alone every
    BSDF without a delta lobe (which would go on along the sharp chain), else with ``lambertian`` the diffuse-only
    ones (docs/maths.md §4.10)."""
    if delta_only:
        return ~mi.has_flag(flags, mi.BSDFFlags.Delta)
    return _diffuse_only(flags) if lambertian else mi.Bool(False)


def _diffuse_only(flags: mi.UInt32) -> mi.Bool:
    """A BSDF with a diffuse reflection lobe and nothing else (no glossy, delta or transmission lobe)."""
    return (mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ~mi.has_flag(flags, mi.BSDFFlags.Glossy)
            & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & ~mi.has_flag(flags, mi.BSDFFlags.DiffuseTransmission))


def _in_stratum(sample: mi.Point2f, cell: mi.Point2f, k: int) -> mi.Point2f:
    """``sample`` moved into ``cell`` of a k x k grid of the unit square, kept below 1 as a sampler's samples are
    (``i + x`` rounds to ``i + 1`` near ``x = 1``)."""
    return dr.minimum((cell + sample) * (1 / k), dr.one_minus_epsilon(mi.Float))


@dr.syntax
def sharp_chain_light(scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, max_depth: int,
                      hide_emitters: bool = False, lambertian_alone: bool = False,
                      emitter_samples: int = 1, stratified: bool = True) -> mi.Spectrum:
    """What a pool's sharp rows leave to camera samples of their own (docs/maths.md §4.10), estimated as
    ``path`` estimates it: along the sharp chain of ``ray`` (through delta lobes only), the emission at every
    vertex, and at every vertex with a smooth lobe one emitter sample and one BSDF sample, power heuristic.
    The walk ends at the first BSDF sample of a smooth lobe, after counting the emission it reaches. Where every
    emitter is a delta one a vertex without a delta lobe takes the emitter sample alone (a BSDF sample would find
    nothing); with ``lambertian_alone`` (only where :func:`emitter_samples_suffice`) so does a Lambertian vertex.
    ``emitter_samples`` ``k``: emitter samples per vertex (one camera ray for several), each weighed by ``1/k``
    and the power heuristic with the sample counts, ``(k p_e)^2 / ((k p_e)^2 + p_b^2)``; ``stratified``: the ``k``
    samples of a vertex are Latin hypercube samples of their 2D square.

    Depths as the pool's: a vertex at depth ``d`` is visited when ``d < max_depth`` and samples direct light
    when ``d + 1 < max_depth``. With ``hide_emitters`` the first ray passes through area emitters and
    emission seen straight from the sensor is not counted, as in the pool's walks."""
    from ..samplers.walk import _interaction as vertex_of
    from ..samplers.walk import first_intersection

    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    n = dr.width(ray.o)
    k = int(emitter_samples)
    strata = k > 1 and stratified
    delta_only = only_delta_emitters(scene)
    lambertian = lambertian_alone and emitter_samples_suffice(scene)
    ray = mi.Ray3f(ray)
    active = dr.full(mi.Bool, True, n)
    pi = first_intersection(scene, ray, active, hide_emitters, coherent=True)
    si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
    result = dr.zeros(mi.Spectrum, n)
    beta = mi.Spectrum(1)
    depth = mi.UInt32(0)
    prev_si = dr.zeros(mi.Interaction3f, n)  # what the emitter densities need of the previous vertex
    prev_pdf = dr.full(mi.Float, 1.0, n)
    prev_delta = dr.full(mi.Bool, True, n)
    limit = dr.opaque(mi.UInt32, max_depth)
    while active:
        # emission here: weight 1 behind delta lobes, else MIS against the emitter sample from prev_si
        emitter = si.emitter(scene, active)
        shown = active & (emitter != None)  # noqa: E711 (Dr.Jit pointer test)
        if hide_emitters:
            shown &= depth > 0
        ds = mi.DirectionSample3f(scene, si, prev_si)
        p_e = scene.pdf_emitter_direction(prev_si, ds, shown & ~prev_delta)
        w = dr.select(prev_delta, 1.0, _power_heuristic(prev_pdf, k * p_e))
        result += dr.select(shown, beta * emitter.eval(si, shown) * w, 0)
        # a sample of a smooth lobe ended the chain; else go on where a further segment may start
        active &= prev_delta & si.is_valid() & (depth + 1 < limit)
        bsdf = si.bsdf(ray)
        smooth = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        # where the BSDF sample would cost a ray for light the emitter samples find as well (or none at all),
        # the emitter samples alone, weight 1
        alone = smooth & _emitter_sample_alone(bsdf.flags(), delta_only, lambertian)
        if dr.hint(strata, mode='scalar'):
            # Latin hypercube samples: sample i takes stratum i of the first dimension (which picks the emitter,
            # then the point on it) and stratum (a i + s) mod k of the second, a random permutation (s uniform; a
            # odd where k is a power of two, else 1); each sample is uniform in its stratum of measure 1/k, so
            # their mean keeps the expectation of independent samples, weights unchanged (docs/maths.md §4.10).
            shift = mi.UInt32(dr.minimum(sampler.next_1d(smooth) * k, k - 1))
            odd = mi.UInt32(1)
            if dr.hint(k & (k - 1) == 0, mode='scalar'):
                odd = 2 * mi.UInt32(dr.minimum(sampler.next_1d(smooth) * (k // 2), k // 2 - 1)) + 1
        for i in range(k):
            sample = sampler.next_2d(smooth)
            if dr.hint(strata, mode='scalar'):
                sample = _in_stratum(sample, mi.Point2f(i, (odd * i + shift) % k), k)
            ds, em_weight = scene.sample_emitter_direction(si, sample, True, smooth)
            lit = smooth & (ds.pdf > 0)
            f, pdf_b = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), lit)
            w_e = dr.select(ds.delta | alone, 1.0, _power_heuristic(k * ds.pdf, pdf_b))
            result += dr.select(lit, beta * f * em_weight * (w_e / k), 0)
        active &= ~alone
        bs, weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
        beta *= weight
        prev_si = vertex_of(si)
        prev_pdf = bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        active &= (bs.pdf > 0) & dr.any(mi.unpolarized_spectrum(beta) != 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        pi = scene.ray_intersect_preliminary(ray, active=active)
        # a smooth lobe's sample counts only the emission it finds: its surface is needed only on an emitter
        # (or an environment, where it escapes)
        active &= prev_delta | ~pi.is_valid() | (pi.shape.emitter() != None)  # noqa: E711
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        depth += 1
    return result
