"""Segment populations: what the segment samplers leave behind for the filtering estimators.

A ``SegmentRecorder`` watches a camera or a light walk and keeps one record per (generalized) segment. Each
record stores the walk vertex the segment *arrives* at (its end ``y`` for camera segments, its start ``x``
for light segments, which run from the light side in walk order) in a compact surface form, so that BSDFs can
be evaluated there later, plus the segment's other end, directions, chain throughput and technique data.
``SegmentPool.build`` joins camera and light records into one struct of arrays in *camera orientation*
(every segment runs from ``x`` on the camera side to ``y`` on the light side; docs/maths.md
§1), with each end's surface referenced by record index.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import drjit as dr
import mitsuba as mi

from .samplers.walk import Vertex

INVALID = 0xFFFFFFFF
CAMERA, LIGHT = 0, 1


@dataclass
class Surface:
    """Enough of a ``SurfaceInteraction3f`` to evaluate a BSDF or an emitter again (~80 B)."""

    p: mi.Point3f
    n: mi.Normal3f
    s: mi.Vector3f
    t: mi.Vector3f
    sn: mi.Normal3f
    uv: mi.Point2f
    shape: mi.ShapePtr
    time: mi.Float
    wavelengths: object
    valid: mi.Bool
    smooth: mi.Bool  #: the BSDF has a non-delta lobe

    @staticmethod
    def of(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr) -> Surface:
        return Surface(p=si.p, n=si.n, s=si.sh_frame.s, t=si.sh_frame.t, sn=si.sh_frame.n, uv=si.uv,
                       shape=si.shape, time=si.time, wavelengths=si.wavelengths if mi.is_spectral else None,
                       valid=si.is_valid(),
                       smooth=si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth))

    def interaction(self, wi_world: mi.Vector3f) -> mi.SurfaceInteraction3f:
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(self.p))
        si.p, si.n, si.uv, si.shape, si.time = self.p, self.n, self.uv, self.shape, self.time
        if self.wavelengths is not None:
            si.wavelengths = self.wavelengths
        si.sh_frame = mi.Frame3f(self.s, self.t, self.sn)
        si.t = dr.select(self.valid, 1.0, dr.inf)
        si.wi = si.to_local(wi_world)
        return si


def _gather(cls, src, index: mi.UInt32, active: mi.Bool | bool = True):
    out = {}
    for f in fields(cls):
        v = getattr(src, f.name)
        if isinstance(v, Surface):
            out[f.name] = _gather(Surface, v, index, active)
        elif v is None:  # wavelengths outside spectral variants
            out[f.name] = None
        else:
            out[f.name] = dr.gather(type(v), v, index, active)
    return cls(**out)


def _select(mask: mi.Bool, a: Surface, b: Surface) -> Surface:
    return Surface(**{f.name: None if getattr(a, f.name) is None
                      else dr.select(mask, getattr(a, f.name), getattr(b, f.name)) for f in fields(Surface)})


def _cat(values: list):
    """Concatenate Dr.Jit arrays along the lane axis (``dr.concat`` joins the outer axis of vectors). The
    offsets are opaque: ``dr.concat`` bakes them into its kernels as constants, which then compile anew for
    every pass (their sizes are random)."""
    tp = type(values[0])
    if dr.depth_v(tp) > 1:
        return tp(*[_cat([v[i] for v in values]) for i in range(dr.size_v(tp))])
    widths = [dr.width(v) for v in values]
    out = dr.zeros(tp, sum(widths))
    offset = 0
    for v, w in zip(values, widths, strict=True):
        if w:
            dr.scatter(out, v, dr.arange(dr.uint32_array_t(tp), w) + dr.opaque(dr.uint32_array_t(tp), offset))
        offset += w
    return out


def _concat(cls, parts: list):
    out = {}
    for f in fields(cls):
        values = [getattr(p, f.name) for p in parts]
        if isinstance(values[0], Surface):
            out[f.name] = _concat(Surface, values)
        elif values[0] is None or len(values) == 1:
            out[f.name] = values[0]
        else:
            out[f.name] = _cat(values)
    return cls(**out)


@dataclass
class Records:
    """Per-segment data in walk orientation (one entry per recorded segment)."""

    surf: Surface  #: the vertex the walk arrived at
    origin: mi.Point3f  #: the segment's other end (walk origin side)
    origin_n: mi.Normal3f
    d_first: mi.Vector3f  #: direction leaving the origin
    d_arrive: mi.Vector3f  #: direction of travel arriving at ``surf``
    chain: mi.Spectrum
    lead: mi.Spectrum
    private: mi.Bool
    index: mi.UInt32
    parent: mi.UInt32  #: record of the previous segment of the same walk, or INVALID
    attempt: mi.Bool  #: the walk tried to continue from ``surf`` (a technique of the MMIS denominator)
    q: mi.Float  #: survival probability of that attempt
    le: mi.Spectrum  #: camera: emission at ``surf`` toward the origin; light: emission of the emitter (index 0)
    emit_factor: mi.Float  #: emission-technique density / (N_e cos_x) of this segment (0: not emissive)
    delta_emit: mi.Bool  #: emitted by a delta emitter: only the emission technique can produce it
    pixel: mi.UInt32  #: camera: the wavefront lane (sample) it belongs to
    pdf: mi.Float  #: solid-angle density of ``d_first`` at the origin (1 for a first segment)
    straight: mi.Bool  #: one straight ray (no delta vertex absorbed)
    sharp: mi.Bool  #: camera: reached from the sensor through delta lobes only (docs/maths.md §4.7)
    depth: mi.UInt32  #: walk depth of ``surf``
    emitter: mi.EmitterPtr  #: the emitter at the segment's light-side end (camera: at ``surf``; light: index 0)
    emit_uv: mi.Point2f  #: light: surface coordinates of the emitter point of a first segment


def _selection_pdf(scene: mi.Scene, emitter: mi.EmitterPtr) -> mi.Float:
    """Probability that ``scene.sample_emitter`` picks ``emitter`` (emitters can carry sampling weights)."""
    pdf = dr.zeros(mi.Float, dr.width(emitter))
    for i, e in enumerate(scene.emitters()):
        pdf = dr.select(emitter == mi.EmitterPtr(e), scene.pdf_emitter(i), pdf)
    return pdf


def emission_density(scene: mi.Scene, ds: mi.DirectionSample3f, ref: mi.Interaction3f,
                     active: mi.Bool) -> mi.Float:
    """Density of the emission technique for emitting from the emitter point ``ds`` toward ``ref``, divided by
    ``N_e cos_x`` (docs/maths.md §3.3); 0 for delta emitters, whose segments only this technique can produce.

    Area lights emit from positions with density ``sel p_A`` and cosine-distributed directions: ``sel p_A / π``.
    ``p_A`` is the shape's area density for uniform radiance (``pdf_direction`` would be a solid-angle density
    of whatever the shape samples from a reference point, e.g. a sphere's visible cap), and comes from
    ``pdf_direction`` (which then matches the texture-proportional position sampling) for spatially varying
    radiance. Environment lights sample a direction, then a point on a disk of the scene's bounding-sphere
    radius ``R``: ``sel p_ω / (π R²)``."""
    emitter = ds.emitter
    flags = emitter.flags()
    active = active & (emitter != None) & ~mi.has_flag(flags, mi.EmitterFlags.Delta)  # noqa: E711
    infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)
    varying = mi.has_flag(flags, mi.EmitterFlags.SpatiallyVarying) & ~infinite
    sel = _selection_pdf(scene, emitter)
    pdf_dir = sel * emitter.pdf_direction(ref, ds, active & (infinite | varying))
    radius = scene.bbox().bounding_sphere().radius
    env = pdf_dir / (dr.pi * dr.square(radius))
    textured = pdf_dir * dr.abs(dr.dot(ds.n, ds.d)) / dr.maximum(dr.square(ds.dist), 1e-20) / dr.pi
    uniform = sel * emitter.get_shape().pdf_position(ds, active & ~infinite & ~varying) / dr.pi
    return dr.select(active, dr.select(infinite, env, dr.select(varying, textured, uniform)), 0)


def _emission_factor(scene: mi.Scene, si: mi.SurfaceInteraction3f, ref: mi.Interaction3f,
                     active: mi.Bool) -> mi.Float:
    """:func:`emission_density` of the emitter surface (or environment) at ``si``, seen from ``ref``."""
    return emission_density(scene, mi.DirectionSample3f(scene, si=si, ref=ref), ref, active)


class SegmentRecorder:
    """Collects the segments of one walk (consumer of ``RandomWalk`` vertices)."""

    def __init__(self, scene: mi.Scene, kind: int, n: int, emitter: mi.EmitterPtr | None = None,
                 emitted_weight: mi.Spectrum | None = None):
        self.scene, self.kind, self.n = scene, kind, n
        self.parts: list[Records] = []
        self.count = 0
        self.last = dr.full(mi.UInt32, INVALID, n)
        self.emit_parts: list[tuple[mi.UInt32, Surface]] = []  #: light: see :meth:`emitter_surfaces`
        self.last_parent = dr.full(mi.UInt32, INVALID, n)  #: parent of ``last``, for segments that absorbed its end
        if kind == LIGHT:
            self.delta = mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
            self.emitted_weight = emitted_weight
            self.emit_le = dr.zeros(mi.Spectrum, n)
            self.emit_factor = dr.zeros(mi.Float, n)
            self.emit_n = dr.zeros(mi.Normal3f, n)
            self.emit_uv = dr.zeros(mi.Point2f, n)
            self.emitter = emitter
            # the emitter's own surface at the emitted point: a first light segment gathers there when the
            # emitter reflects light too (its BSDF has a non-delta lobe)
            self.emit_surf: Surface | None = None
        # camera: the lane's segments so far all left delta lobes (the first segment leaves the sensor)
        self.sharp = dr.full(mi.Bool, kind == CAMERA, n)

    def visit(self, v: Vertex) -> None:
        scene, si = self.scene, v.si
        if self.kind == LIGHT:
            # At the first hit, look back at the emitter: its radiance toward the hit, its normal and the
            # emission technique's density (the emitted ray itself carries only the combined weight).
            first = v.active & (v.depth == 1) & ~self.delta
            back = si.spawn_ray(-v.ray.d)
            si_e = scene.ray_intersect(back, first)
            ref = dr.zeros(mi.Interaction3f, dr.width(si.p))
            ref.p, ref.n, ref.time, ref.wavelengths = si.p, si.n, si.time, si.wavelengths
            em = si_e.emitter(scene)
            self.emit_le = dr.select(first, em.eval(si_e, first), self.emit_le)
            self.emit_factor = dr.select(first, _emission_factor(scene, si_e, ref, first), self.emit_factor)
            self.emit_n = dr.select(first, si_e.n, self.emit_n)
            self.emit_uv = dr.select(first, si_e.uv, self.emit_uv)
            bsdf_e = si_e.bsdf()
            here = Surface.of(si_e, bsdf_e)
            # black emitter surfaces (most area lights) reflect nothing: no query there
            probe = mi.SurfaceInteraction3f(si_e)
            probe.wi = mi.Vector3f(0, 0, 1)
            f = bsdf_e.eval(mi.BSDFContext(), probe, mi.Vector3f(0, 0, 1), first)
            here.smooth &= (dr.any(mi.unpolarized_spectrum(f) > 0)
                            | mi.has_flag(bsdf_e.flags(), mi.BSDFFlags.Glossy))
            self.emit_surf = here if self.emit_surf is None else _select(first, here, self.emit_surf)
            dr.schedule(self.emit_le, self.emit_factor, self.emit_n, self.emit_uv, self.emit_surf)

        record = v.ends_segment
        if self.kind == LIGHT:
            record &= si.is_valid()  # an escaped light segment starts nowhere
        seg = v.segment
        if self.kind == CAMERA:
            ds = mi.DirectionSample3f(scene, si=si, ref=v.prev)
            le = ds.emitter.eval(si, v.active)
            emit_factor = _emission_factor(scene, si, v.prev, v.active & (seg.index > 0))
            delta_emit = dr.zeros(mi.Bool, self.n)
            origin_n = seg.origin_n
            emitter = ds.emitter
            emit_uv = si.uv
        else:
            first_seg = seg.index == 0
            le = dr.select(first_seg, dr.select(self.delta, self.emitted_weight, self.emit_le), 0)
            emit_factor = dr.select(first_seg & ~self.delta, self.emit_factor, 0)
            delta_emit = first_seg & self.delta
            origin_n = dr.select(first_seg, self.emit_n, seg.origin_n)
            emitter = dr.select(first_seg, self.emitter, mi.EmitterPtr(None))
            emit_uv = self.emit_uv
        # Everything the records take from the (lazily traced) vertex, evaluated in one kernel: gathering each
        # field from the lazy interaction would trace the rays again for every field.
        surf = Surface.of(si, v.bsdf)
        sharp = self.sharp & ((seg.index == 0) | seg.private)
        self.sharp = dr.select(record, sharp, self.sharp)
        # a segment that absorbed the end of the last one (docs/maths.md §2.3) starts where that one started
        parent = dr.select(seg.absorbed, self.last_parent, self.last)
        dr.eval(surf, le, emit_factor, delta_emit, origin_n, record, sharp, self.sharp, emitter, emit_uv, parent)
        idx = dr.compress(record)
        m = dr.width(idx)
        if m == 0:
            return

        def g(x):
            return dr.gather(type(x), x, idx)

        rec = Records(
            surf=_gather(Surface, surf, idx),
            origin=g(seg.origin), origin_n=g(origin_n), d_first=g(seg.direction), d_arrive=g(v.ray.d),
            chain=g(seg.chain), lead=g(seg.lead), private=g(seg.private), index=g(seg.index),
            parent=g(parent), attempt=g(v.continues), q=g(v.q), le=g(le), emit_factor=g(emit_factor),
            delta_emit=g(delta_emit), pixel=idx, pdf=g(seg.pdf), straight=g(seg.straight), sharp=g(sharp),
            depth=g(v.depth), emitter=g(emitter), emit_uv=g(emit_uv),
        )
        if self.kind == LIGHT and self.emit_surf is not None:
            reflects = g(first_seg & ~self.delta & self.emit_surf.smooth)
            at = dr.compress(reflects)
            if dr.width(at):
                lanes = dr.gather(mi.UInt32, idx, at)
                self.emit_parts.append((at + dr.opaque(mi.UInt32, self.count), _gather(Surface, self.emit_surf, lanes)))
        dr.eval(rec)  # reads self.last: evaluate before it is updated
        # opaque: the running count must not be a kernel constant (a new compile every bounce and pass)
        dr.scatter(self.last_parent, rec.parent, idx)
        dr.scatter(self.last, dr.arange(mi.UInt32, m) + dr.opaque(mi.UInt32, self.count), idx)
        dr.eval(self.last, self.last_parent)
        self.count += m
        self.parts.append(rec)

    def records(self) -> Records | None:
        return _concat(Records, self.parts) if self.parts else None

    def emitter_surfaces(self) -> tuple[mi.UInt32, Surface] | None:
        """Light: (record index, emitter surface) of the first segments whose emitter reflects light."""
        if not self.emit_parts:
            return None
        return _cat([p[0] for p in self.emit_parts]), _concat(Surface, [p[1] for p in self.emit_parts])


@dataclass
class SegmentPool:
    """All segments of a pass in camera orientation (``x`` camera side, ``y`` light side).

    ``surf`` holds the walk-arrival surface of every record; ``x_surf``/``y_surf`` index into it (INVALID:
    sensor, emitter, or escape)."""

    surf: Surface
    kind: mi.UInt32
    x: mi.Point3f
    nx: mi.Normal3f
    wx: mi.Vector3f  #: direction at x toward y
    y: mi.Point3f
    ny: mi.Normal3f
    dy: mi.Vector3f  #: direction at y toward x
    x_surf: mi.UInt32
    y_surf: mi.UInt32
    chain: mi.Spectrum
    lead: mi.Spectrum
    private: mi.Bool
    parent: mi.UInt32
    index: mi.UInt32
    attempt: mi.Bool
    q: mi.Float
    le: mi.Spectrum
    emit_factor: mi.Float
    delta_emit: mi.Bool
    pixel: mi.UInt32
    pdf: mi.Float
    straight: mi.Bool
    sharp: mi.Bool
    depth: mi.UInt32
    emitter: mi.EmitterPtr  #: the emitter at ``y`` (None where ``y`` emits nothing)
    emit_uv: mi.Point2f  #: surface coordinates there
    camera_count: int
    light_count: int
    #: emitter surfaces of first light segments (``y_surf`` >= ``size`` indexes them), or None
    emitter_surf: Surface | None = None

    @property
    def size(self) -> int:
        return self.camera_count + self.light_count

    @staticmethod
    def build(scene: mi.Scene, camera: Records | None, light: Records | None,
              emitter_surfaces: tuple[mi.UInt32, Surface] | None = None) -> SegmentPool:
        """``emitter_surfaces``: (light record index, surface) of the first light segments whose emitter
        reflects (:meth:`SegmentRecorder.emitter_surfaces`); they become queries at the emitter (their ``y``)."""
        parts, kinds = [], []
        nc = dr.width(camera.index) if camera is not None else 0
        nl = dr.width(light.index) if light is not None else 0
        if camera is not None:
            parts.append(camera)
            kinds.append(dr.full(mi.UInt32, CAMERA, nc))
        if light is not None:
            lp = dr.select(light.parent == INVALID, INVALID, light.parent + dr.opaque(mi.UInt32, nc))
            parts.append(Records(**{**{f.name: getattr(light, f.name) for f in fields(Records)}, "parent": lp}))
            kinds.append(dr.full(mi.UInt32, LIGHT, nl))
        r = _concat(Records, parts)
        kind = kinds[0] if len(kinds) == 1 else _cat(kinds)
        cam = kind == CAMERA
        own = dr.arange(mi.UInt32, nc + nl)
        # Camera: x = origin (parent's arrival, or the sensor), y = arrival. Light: x = arrival, y = origin.
        pool = SegmentPool(
            surf=r.surf, kind=kind,
            x=dr.select(cam, r.origin, r.surf.p), nx=dr.select(cam, r.origin_n, r.surf.n),
            wx=dr.select(cam, r.d_first, -r.d_arrive),
            y=dr.select(cam, r.surf.p, r.origin), ny=dr.select(cam, r.surf.n, r.origin_n),
            dy=dr.select(cam, -r.d_arrive, r.d_first),
            x_surf=dr.select(cam, r.parent, own), y_surf=dr.select(cam, own, r.parent),
            chain=r.chain, lead=r.lead, private=r.private, parent=r.parent, index=r.index, attempt=r.attempt,
            q=r.q, le=r.le, emit_factor=r.emit_factor, delta_emit=r.delta_emit, pixel=r.pixel,
            pdf=r.pdf, straight=r.straight, sharp=r.sharp, depth=r.depth,
            emitter=r.emitter, emit_uv=dr.select(cam, r.surf.uv, r.emit_uv), camera_count=nc, light_count=nl,
        )
        # Light segments whose y lies on an emitter (light that bounced back onto one) carry its emission.
        if nl:
            has_y = ~cam & (pool.y_surf != INVALID)  # before the emitter surfaces join: walk surfaces only
            ys = _gather(Surface, r.surf, pool.y_surf, has_y)
            si_y = ys.interaction(pool.dy)
            em = si_y.shape.emitter()
            lit = has_y & ys.valid & (em != None)  # noqa: E711 (Dr.Jit pointer test)
            pool.le = dr.select(lit, em.eval(si_y, lit), pool.le)
            pool.emitter = dr.select(lit, em, pool.emitter)
            pool.emit_uv = dr.select(lit, ys.uv, pool.emit_uv)
            # ... and the emission technique could have produced them too: it belongs in their denominator.
            ref = dr.zeros(mi.Interaction3f, nc + nl)
            ref.p = pool.x
            pool.emit_factor = dr.select(lit, _emission_factor(scene, si_y, ref, lit), pool.emit_factor)
        if nl and emitter_surfaces is not None:
            at, surfaces = emitter_surfaces
            dr.scatter(pool.y_surf, dr.arange(mi.UInt32, dr.width(at)) + dr.opaque(mi.UInt32, nc + nl),
                       at + dr.opaque(mi.UInt32, nc))
            pool.emitter_surf = surfaces
        dr.eval(pool.le, pool.emit_factor, pool.emitter, pool.emit_uv, pool.x, pool.nx, pool.wx, pool.y, pool.ny,
                pool.dy, pool.x_surf, pool.y_surf)
        return pool

    def end_surface(self, which: str, index: mi.UInt32, active: mi.Bool) -> Surface:
        ref = self.x_surf if which == "x" else self.y_surf
        s = dr.gather(mi.UInt32, ref, index, active)
        size = dr.opaque(mi.UInt32, self.size)  # opaque: the pool's size must not be a kernel constant
        walk = _gather(Surface, self.surf, s, active & (s < size))
        if self.emitter_surf is None or which == "x":
            return walk
        on_emitter = active & (s != INVALID) & (s >= size)
        emitter = _gather(Surface, self.emitter_surf, s - size, on_emitter)
        return _select(on_emitter, emitter, walk)
