"""The sequential segment sampler's random walk, shared by the camera and the light sampler.

Both forms of the walk run the same two steps per vertex (``arrive``: what the vertex is; ``leave``: the
BSDF sample that continues from it). ``run`` is a wavefront loop in Python, one vertex per iteration with its
state evaluated once per bounce (as in Mitsuba's wavefront mode), that *yields* every vertex it reaches, so
that the sequential estimators (emission, emitter sampling, sensor connections) consume the walk without
owning it. ``run_symbolic`` is one symbolic loop (one kernel for the whole walk, as Mitsuba's own
integrators) that hands every vertex to a consumer traced into the loop body: the population recorder, which
writes the segments for the filtering estimators from inside the walk's kernel.

Generalized segments (docs/maths.md §2): a segment runs from one *segment vertex* to the
next; a vertex is a segment vertex when its BSDF has a non-delta lobe, when it is emissive, or when the walk
escapes or stops there. Purely delta vertices (mirror, smooth glass) are absorbed into the segment: their
weights form the segment's chain throughput. Russian roulette is applied only at segment vertices, so each
segment has one well-defined survival probability ``q`` for its attempt to spawn a child.

Depths follow Mitsuba: a vertex at depth ``d`` closes a path of ``d + 1`` segments between sensor and
emitter, it is visited when ``d < max_depth``, and the walk continues from it only when
``d + 1 < max_depth``. The camera walk starts at depth 0, the light walk at depth 1 (the emitter is 0).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi


@dataclass
class SegmentState:
    """The (generalized) segment that arrives at the current vertex, in walk orientation."""

    origin: mi.Point3f  #: where it starts (segment vertex, sensor or emitter point)
    origin_n: mi.Normal3f  #: geometric normal there (0 at a sensor or a delta-position emitter)
    direction: mi.Vector3f  #: its first direction, leaving ``origin``
    chain: mi.Spectrum  #: product of the delta-vertex weights inside the segment
    lead: mi.Spectrum  #: BSDF weight / survival probability of the sample at ``origin`` that started it
    #: its own path's only, never gathered: it left a mixed vertex through a delta lobe, or (camera pools with
    #: private glossy vertices) a glossy vertex
    private: mi.Bool
    index: mi.UInt32  #: 0 for the first segment of a walk
    pdf: mi.Float  #: solid-angle density of ``direction`` at ``origin`` (1 for the first segment)
    straight: mi.Bool  #: no delta vertex absorbed yet: the segment is one straight ray
    absorbed: mi.Bool  #: it went on through the delta lobe of a mixed vertex, which it absorbed (§2.3)
    sharp: mi.Bool  #: every segment of the walk so far left a delta lobe (the first leaves the sensor or light)


@dataclass
class Vertex:
    """One vertex a walk reached (or the escape of its ray), as estimators see it."""

    si: mi.SurfaceInteraction3f  #: ``si.wi`` points back along the walk
    bsdf: mi.BSDFPtr
    ray: mi.Ray3f  #: the ray that found the vertex
    throughput: mi.Spectrum  #: walk weight up to this vertex (its own BSDF not included)
    depth: mi.UInt32
    active: mi.Bool  #: lanes whose walk reached this vertex (a surface or an escape)
    prev: mi.Interaction3f  #: previous vertex, for emitter MIS
    prev_pdf: mi.Float  #: solid-angle density of the direction that led here
    prev_delta: mi.Bool  #: that direction came from a delta lobe
    ends_segment: mi.Bool  #: a segment ends here
    continues: mi.Bool  #: the walk will try to continue from here (before Russian roulette)
    q: mi.Float  #: survival probability of that attempt (1 before ``rr_depth`` and inside delta chains)
    segment: SegmentState
    delta_only: mi.Bool  #: past the segment limit: the walk continues only through a delta lobe
    #: a segment ends here that is not kept (a walk keeping only delta chains reached a mixed vertex straight):
    #: the walk goes on only through the vertex's delta lobe, absorbing it into the next segment
    dropped: mi.Bool


@dataclass
class WalkState:
    """What a walk carries from one vertex to the next (the loop state of the symbolic walk)."""

    ray: mi.Ray3f
    pi: mi.PreliminaryIntersection3f  #: where ``ray`` hits
    beta: mi.Spectrum
    eta: mi.Float
    depth: mi.UInt32
    active: mi.Bool
    prev: mi.Interaction3f
    prev_pdf: mi.Float
    prev_delta: mi.Bool
    segment: SegmentState


def _interaction(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f)
    it.p, it.n, it.t, it.time, it.wavelengths = si.p, si.n, si.t, si.time, si.wavelengths
    return it


def glossy_vertex(bsdf: mi.BSDFPtr) -> mi.Bool:
    """A BSDF with a glossy lobe and no delta lobe: where filters with private glossy vertices do not gather
    (docs/maths.md §4.8)."""
    flags = bsdf.flags()
    return mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Delta)


def intersect_skipping_emitters(scene: mi.Scene, ray: mi.Ray3f, active: mi.Bool,
                                coherent: bool = False) -> mi.PreliminaryIntersection3f:
    """First intersection that is not an area emitter (Mitsuba's ``hide_emitters`` for area lights);
    ``coherent``: rays from the sensor (see :func:`first_intersection`)."""
    pi = scene.ray_intersect_preliminary(ray, coherent=coherent, active=active)
    skip = active & pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711 (Dr.Jit pointer test)
    r = mi.Ray3f(ray)
    for _ in range(8):  # emitters stacked along one ray are rare; bound the work
        if not dr.any(skip):
            break
        si = pi.compute_surface_interaction(r, mi.RayFlags.Minimal, skip)
        r = dr.select(skip, si.spawn_ray(ray.d), r)
        pi_next = scene.ray_intersect_preliminary(r, active=skip)
        pi[skip] = pi_next
        skip &= pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711
        dr.eval(pi, r, skip)
    return pi


def first_intersection(scene: mi.Scene, ray: mi.Ray3f, active: mi.Bool, hide_emitters: bool = False,
                       coherent: bool = False) -> mi.PreliminaryIntersection3f:
    """Where ``ray`` first hits (past area emitters with ``hide_emitters``). ``coherent``: the rays leave the
    sensor, neighbouring lanes through neighbouring pixels, and go to Embree as coherent rays, as ``path`` traces
    its first rays (docs/maths.md §4.10)."""
    if hide_emitters:
        return intersect_skipping_emitters(scene, ray, active, coherent)
    return scene.ray_intersect_preliminary(ray, coherent=coherent, active=active)


class RandomWalk:
    """Sequential segment sampler: BSDF-sampled continuation of camera or light sub-paths."""

    def __init__(self, mode: mi.TransportMode, max_depth: int, rr_depth: int, max_segments: int = 0xFFFFFFFF,
                 keep_zero_weight: bool = False, follow_delta_lobes: bool = False, absorb_delta_lobes: bool = False,
                 drop_delta_lobes: bool = False, private_glossy: bool = False, delta_chains_only: bool = False):
        """``keep_zero_weight``: continue walks whose throughput became zero (a black surface, a shading-normal
        leak) while the BSDF sample itself succeeded. Sequential estimators stop them (they carry nothing); a
        segment *pool* must keep them, because the child is a sample of a technique that the MMIS
        denominator counts, and other segments gather it whatever its own throughput."""
        self.keep_zero_weight = keep_zero_weight
        #: past ``max_segments``, still continue through the delta lobes of mixed vertices (private segments)
        self.follow_delta_lobes = follow_delta_lobes
        #: a walk that leaves a mixed vertex through its delta lobe absorbs the vertex into its segment, as it
        #: absorbs purely delta vertices; the segment that ended there stays recorded (docs/maths.md §2.3)
        self.absorb_delta_lobes = absorb_delta_lobes
        #: a walk whose segments did not all leave delta lobes stops where it samples the delta lobe of a
        #: mixed, non-emissive vertex: the other side's walks carry those paths, absorbed (docs/maths.md §2.3)
        self.drop_delta_lobes = drop_delta_lobes
        #: segments that leave a vertex with a glossy lobe (and no delta one) are private: the filters do not
        #: gather there, the walk's own continuation carries the light (docs/maths.md §4.8)
        self.private_glossy = private_glossy
        #: past its first segment, a walk keeps only segments through a delta vertex, and stops where a segment
        #: would reach a vertex straight: the other side's walks make those (docs/maths.md §2.5)
        self.delta_chains_only = delta_chains_only
        self.mode = mode
        self.ctx = mi.BSDFContext(mode)
        self.max_depth = max_depth  # already mapped: -1 -> 2^32 - 1
        self.rr_depth = rr_depth
        self.max_segments = max_segments

    def run(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, throughput: mi.Spectrum,
            start_depth: int, active: mi.Bool, origin_n: mi.Normal3f | None = None,
            hide_first_emitters: bool = False) -> Iterator[Vertex]:
        """Walk from ``ray``; yields one ``Vertex`` per bounce until every lane has stopped."""
        state = self.start(scene, ray, throughput, start_depth, active, origin_n, hide_first_emitters)
        while True:
            vertex = self.arrive(state)
            yield vertex
            state = self.leave(scene, sampler, state, vertex)
            sampler.schedule_state()
            dr.eval(state)
            if not dr.any(state.active):
                break

    def run_symbolic(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, throughput: mi.Spectrum,
                     start_depth: int, active: mi.Bool, visit: Callable[[Vertex, Any], Any], visit_state: Any,
                     before_chunk: Callable[[int], None] | None = None, chunk: int = 8,
                     origin_n: mi.Normal3f | None = None, hide_first_emitters: bool = False) -> Any:
        """Walk from ``ray`` in symbolic loops of up to ``chunk`` vertices, one kernel each, calling
        ``visit(vertex, visit_state) -> visit_state`` inside the loop body (it must not evaluate anything).
        ``before_chunk(vertices)`` runs before each loop (for instance, to make room for what the consumer
        writes). Returns the final ``visit_state``."""
        state = self.start(scene, ray, throughput, start_depth, active, origin_n, hide_first_emitters)
        done = 0
        while True:
            steps = max(0, min(chunk, self.max_depth - start_depth - done))
            if before_chunk is not None:
                before_chunk(steps)
            # every lane's depth moves on by one per iteration: the chunk ends at one common depth
            stop = dr.opaque(mi.UInt32, start_depth + done + steps)

            def body(sampler, state, visit_state):
                vertex = self.arrive(state)
                visit_state = visit(vertex, visit_state)
                return sampler, self.leave(scene, sampler, state, vertex), visit_state

            sampler, state, visit_state = dr.while_loop(
                (sampler, state, visit_state), lambda sampler, state, _, stop=stop: state.active & (state.depth < stop),
                body, label="segment walk")
            sampler.schedule_state()
            done += steps
            if done >= self.max_depth - start_depth:
                # the last loop: its walk state goes nowhere, and a kernel's outputs are streaming stores, much
                # dearer per byte past a few streams (README, thirty-first run): write only what is kept
                dr.eval(visit_state)
                return visit_state
            dr.eval(state, visit_state)
            if not dr.any(state.active):
                return visit_state

    def record(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, throughput: mi.Spectrum,
               start_depth: int, active: mi.Bool, recorder: Any, hide_first_emitters: bool = False) -> None:
        """:meth:`run_symbolic` with a recorder as consumer (``initial``, ``visit``, ``reserve``, ``finish``:
        :class:`~segmitsuba.population.SegmentRecorder`)."""
        lanes = self.run_symbolic(scene, sampler, ray, throughput, start_depth, active, recorder.visit,
                                  recorder.initial(), before_chunk=recorder.reserve,
                                  hide_first_emitters=hide_first_emitters)
        recorder.finish(lanes)

    def start(self, scene: mi.Scene, ray: mi.Ray3f, throughput: mi.Spectrum, start_depth: int, active: mi.Bool,
              origin_n: mi.Normal3f | None = None, hide_first_emitters: bool = False) -> WalkState:
        n = dr.width(ray.o)
        depth = dr.full(mi.UInt32, start_depth, n)
        active = mi.Bool(active) & (depth < self.max_depth)
        ray = mi.Ray3f(ray)
        # a camera walk starts at the sensor: its first rays are coherent
        pi = first_intersection(scene, ray, active, hide_first_emitters,
                                coherent=self.mode == mi.TransportMode.Radiance and start_depth == 0)
        seg = SegmentState(
            origin=mi.Point3f(ray.o), origin_n=mi.Normal3f(0) if origin_n is None else mi.Normal3f(origin_n),
            direction=mi.Vector3f(ray.d), chain=mi.Spectrum(1), lead=mi.Spectrum(1),
            private=dr.full(mi.Bool, False, n), index=dr.zeros(mi.UInt32, n),
            pdf=dr.full(mi.Float, 1.0, n), straight=dr.full(mi.Bool, True, n),
            absorbed=dr.full(mi.Bool, False, n), sharp=dr.full(mi.Bool, True, n),
        )
        return WalkState(ray=ray, pi=pi, beta=mi.Spectrum(throughput), eta=dr.full(mi.Float, 1.0, n), depth=depth,
                         active=active, prev=dr.zeros(mi.Interaction3f, n), prev_pdf=dr.full(mi.Float, 1.0, n),
                         prev_delta=dr.full(mi.Bool, True, n), segment=seg)

    def arrive(self, state: WalkState) -> Vertex:
        """The vertex ``state.ray`` reached: its surface, whether a segment ends there and what follows."""
        ray, depth, active, seg = state.ray, state.depth, state.active, state.segment
        si = state.pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        valid = si.is_valid()
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()
        continues = active & valid & (depth + 1 < self.max_depth)
        emissive = valid & (si.shape.emitter() != None)  # noqa: E711
        ends = active & (~valid | mi.has_flag(flags, mi.BSDFFlags.Smooth) | emissive | ~continues)
        dropped = mi.Bool(False)
        if self.delta_chains_only:
            straight = ends & seg.straight & (seg.index > 0)
            # at a mixed vertex the straight segment is not kept, but what leaves its delta lobe is a delta chain
            # that no camera walk makes (docs/maths.md §2.3, §2.5): the walk goes on through that lobe alone
            dropped = straight & continues & mi.has_flag(flags, mi.BSDFFlags.Delta) & ~emissive
            ends &= ~straight | dropped
            continues &= ~straight | dropped
        # past the segment limit only a delta lobe may continue: no technique is attempted there
        delta_only = (continues & ends & ~(seg.index + 1 < self.max_segments)
                      & mi.has_flag(flags, mi.BSDFFlags.Delta)) if self.follow_delta_lobes else mi.Bool(False)
        continues &= ~ends | (seg.index + 1 < self.max_segments)
        # Russian roulette, only where a segment ends, with a probability fixed before sampling: one
        # survival probability per segment, a constant factor of its technique density.
        rr = ends & (depth >= self.rr_depth)
        q = dr.select(rr, dr.minimum(dr.max(mi.unpolarized_spectrum(state.beta)) * dr.square(state.eta), 0.95), 1.0)
        return Vertex(si=si, bsdf=bsdf, ray=ray, throughput=state.beta, depth=depth, active=active,
                      prev=state.prev, prev_pdf=state.prev_pdf, prev_delta=state.prev_delta, ends_segment=ends,
                      continues=continues, q=q, segment=seg, delta_only=delta_only, dropped=dropped)

    def leave(self, scene: mi.Scene, sampler: mi.Sampler, state: WalkState, v: Vertex) -> WalkState:
        """Sample the BSDF at ``v`` (where the walk continues) and trace the next ray."""
        importance = self.mode == mi.TransportMode.Importance
        si, ray, seg = v.si, v.ray, v.segment
        sampling = v.continues | v.delta_only
        bs, weight = v.bsdf.sample(self.ctx, si, sampler.next_1d(sampling), sampler.next_2d(sampling), sampling)
        wo = si.to_world(bs.wo)
        if importance:
            # Adjoint BSDF with shading normals [Veach 1997, p. 155], and no light leaks (as ptracer).
            wi_dot_n = dr.dot(si.n, -ray.d)
            wo_dot_n = dr.dot(si.n, wo)
            ok = (wi_dot_n * mi.Frame3f.cos_theta(si.wi) > 0) & (wo_dot_n * mi.Frame3f.cos_theta(bs.wo) > 0)
            weight *= dr.abs((mi.Frame3f.cos_theta(si.wi) * wo_dot_n)
                             / (mi.Frame3f.cos_theta(bs.wo) * wi_dot_n))
            weight = dr.select(ok, weight, 0)
        delta_lobe = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        emissive = si.is_valid() & (si.shape.emitter() != None)  # noqa: E711
        alive = (v.continues | (v.delta_only & delta_lobe)) & (bs.pdf > 0)
        if self.keep_zero_weight:
            # A BSDF whose sample fails masks its weight and may leave bs.pdf as it was (roughconductor: a
            # reflection below the horizon; roughdielectric: a refraction outside its support): a zero weight
            # whose direction the BSDF's pdf gives no density is no sample, unlike a black surface's (the
            # segment it started had no technique density in D, and gathers divided by almost nothing)
            zero = alive & ~dr.any(mi.unpolarized_spectrum(weight) != 0) & ~delta_lobe
            alive &= ~zero | (v.bsdf.pdf(self.ctx, si, bs.wo, zero) > 0)
        if self.drop_delta_lobes:
            alive &= ~(v.ends_segment & delta_lobe & ~emissive & ~seg.sharp)
        if self.delta_chains_only:
            alive &= ~v.dropped | delta_lobe
        if not self.keep_zero_weight:
            alive &= dr.any(mi.unpolarized_spectrum(weight) != 0)
        alive &= sampler.next_1d(alive) < v.q
        beta = dr.select(alive, state.beta * weight / v.q, 0)

        # a new segment starts here, unless the vertex is absorbed (delta lobe of a mixed vertex)
        absorb = v.ends_segment & delta_lobe & ~emissive & self.absorb_delta_lobes
        new = v.ends_segment & ~absorb
        # not `|=` on delta_lobe: that would change it in place, and `sharp` below reads it
        private = delta_lobe | glossy_vertex(v.bsdf) if self.private_glossy else delta_lobe
        seg = SegmentState(
            origin=dr.select(new, si.p, seg.origin),
            origin_n=dr.select(new, si.n, seg.origin_n),
            direction=dr.select(new, wo, seg.direction),
            chain=dr.select(new, mi.Spectrum(1), seg.chain * dr.select(absorb, weight / v.q, weight)),
            lead=dr.select(new, weight / v.q, seg.lead),
            private=dr.select(new, private, seg.private),
            index=dr.select(new, seg.index + 1, seg.index),
            pdf=dr.select(new, bs.pdf, seg.pdf),
            straight=new,
            absorbed=dr.select(new, False, seg.absorbed | absorb),
            sharp=dr.select(new, seg.sharp & delta_lobe, seg.sharp),
        )
        ray = si.spawn_ray(wo)
        pi = scene.ray_intersect_preliminary(ray, active=alive)
        if self.delta_chains_only:
            # a new segment is straight: :meth:`arrive` drops it unless it reaches a vertex with a delta lobe (not
            # an emitter) that continues, so the walk stops here without computing where it arrives (what arrive
            # reads: the hit shape's BSDF flags and emitter pointer, both per shape)
            through = (pi.is_valid() & mi.has_flag(pi.shape.bsdf().flags(), mi.BSDFFlags.Delta)
                       & (pi.shape.emitter() == None) & (state.depth + 2 < self.max_depth))  # noqa: E711
            alive &= ~new | through
        return WalkState(ray=ray, pi=pi, beta=beta,
                         eta=state.eta * bs.eta, depth=state.depth + 1, active=alive, prev=_interaction(si),
                         prev_pdf=bs.pdf, prev_delta=delta_lobe, segment=seg)
