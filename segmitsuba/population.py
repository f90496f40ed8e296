"""Segment populations: what the segment samplers leave behind for the filtering estimators.

A ``SegmentRecorder`` watches a camera or a light walk and keeps one record per (generalized) segment. Each
record stores the walk vertex the segment *arrives* at (its end ``y`` for camera segments, its start ``x``
for light segments, which run from the light side in walk order) in a compact surface form, so that BSDFs can
be evaluated there later, plus the segment's other end, directions, chain throughput and technique data.
The records of a pool go to one ``RecordBuffer`` (camera walk first, then light walk): each lane that ends a
segment claims a slot with an atomic counter and writes its record there, in the same kernel that traces
the bounce, so that a vertex is traced once and nothing is copied per bounce. ``SegmentPool.build`` turns
the buffer into one struct of arrays in *camera orientation* (every segment runs from ``x`` on the camera
side to ``y`` on the light side; docs/maths.md §1), with each end's surface referenced by record index.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import drjit as dr
import mitsuba as mi

from .samplers.emission import emission_bounds, emitter_class
from .samplers.walk import Vertex

INVALID = 0xFFFFFFFF
#: the kinds of records: camera walks, light walks, next-event segments (docs/maths.md §3.5)
CAMERA, LIGHT, NEXT_EVENT = 0, 1, 2


@dataclass
class Surface:
    """Enough of a ``SurfaceInteraction3f`` to evaluate a BSDF or an emitter again (~70 B)."""

    p: mi.Point3f
    n: mi.Normal3f
    s: mi.Vector3f  #: shading tangent (the bitangent is ``sn x s``: Mitsuba's frames are right-handed)
    sn: mi.Normal3f
    uv: mi.Point2f
    shape: mi.ShapePtr
    time: mi.Float
    wavelengths: object
    valid: mi.Bool
    smooth: mi.Bool  #: the BSDF has a non-delta lobe

    @staticmethod
    def of(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr) -> Surface:
        return Surface(p=si.p, n=si.n, s=si.sh_frame.s, sn=si.sh_frame.n, uv=si.uv,
                       shape=si.shape, time=si.time, wavelengths=si.wavelengths if mi.is_spectral else None,
                       valid=si.is_valid(),
                       smooth=si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth))

    def interaction(self, wi_world: mi.Vector3f) -> mi.SurfaceInteraction3f:
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(self.p))
        si.p, si.n, si.uv, si.shape, si.time = self.p, self.n, self.uv, self.shape, self.time
        if self.wavelengths is not None:
            si.wavelengths = self.wavelengths
        si.sh_frame = mi.Frame3f(self.s, dr.cross(self.sn, self.s), self.sn)
        si.t = dr.select(self.valid, 1.0, dr.inf)
        # where the ray escaped, Mitsuba's convention: the world direction back (what an environment evaluates)
        si.wi = dr.select(self.valid, si.to_local(wi_world), wi_world)
        return si


def _map(obj, fn):
    """``obj`` (a ``Surface`` or ``SegmentPool``) with ``fn`` applied to each of its Dr.Jit arrays; other fields
    (wavelengths outside spectral variants, pool counts) are kept."""
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        out[f.name] = _map(v, fn) if isinstance(v, Surface) else (
            v if v is None or isinstance(v, int) else fn(v))
    return type(obj)(**out)


def _gather(src, index: mi.UInt32, active: mi.Bool | bool = True):
    return _map(src, lambda v: dr.gather(type(v), v, index, active))


def _select(mask: mi.Bool, a: Surface, b: Surface) -> Surface:
    return Surface(**{f.name: None if getattr(a, f.name) is None
                      else dr.select(mask, getattr(a, f.name), getattr(b, f.name)) for f in fields(Surface)})


def _get(obj, name: str):
    """Field ``name`` of a record struct; ``surf.`` names a field of its surface."""
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, name: str, value) -> None:
    *outer, last = name.split(".")
    for part in outer:
        obj = getattr(obj, part)
    setattr(obj, last, value)


def _cat(values: list):
    """Concatenate Dr.Jit arrays along the lane axis (``dr.concat`` joins the outer axis of vectors), as
    lazy gathers, so that the result fuses into the kernel that uses it. The offsets are opaque:
    ``dr.concat`` bakes them into its kernels as constants, which then compile anew for every pass (their
    sizes are random)."""
    tp = type(values[0])
    widths = [dr.width(v) for v in values]
    i = dr.arange(mi.UInt32, sum(widths))
    out, offset = dr.zeros(tp, sum(widths)), 0
    for v, w in zip(values, widths, strict=True):
        if w:
            start = dr.opaque(mi.UInt32, offset)
            inside = (i >= start) & (i < start + dr.opaque(mi.UInt32, w))
            out = dr.select(inside, dr.gather(tp, v, i - start, inside), out)
        offset += w
    return out


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
    radius = emission_bounds(scene).bounding_sphere().radius
    env = pdf_dir / (dr.pi * dr.square(radius))
    textured = pdf_dir * dr.abs(dr.dot(ds.n, ds.d)) / dr.maximum(dr.square(ds.dist), 1e-20) / dr.pi
    uniform = sel * _inverse_area(scene, emitter) / dr.pi
    return dr.select(active, dr.select(infinite, env, dr.select(varying, textured, uniform)), 0)


def _inverse_area(scene: mi.Scene, emitter: mi.EmitterPtr) -> mi.Float:
    """``1 / A`` of each lane's emitter shape (0 without one): Mitsuba's ``pdf_position`` of a shape sampled
    uniformly in area. Looked up per emitter, not through ``ShapePtr.pdf_position``: a call on a shape pointer
    traces the method of every shape of the scene, and instances and curves do not implement it."""
    out = dr.zeros(mi.Float, dr.width(emitter))
    for e in scene.emitters():
        shape = e.get_shape()
        if shape is not None:
            out = dr.select(emitter == mi.EmitterPtr(e), dr.rcp(shape.surface_area()), out)
    return out


def _emission_factor(scene: mi.Scene, si: mi.SurfaceInteraction3f, ref: mi.Interaction3f,
                     active: mi.Bool) -> mi.Float:
    """:func:`emission_density` of the emitter surface (or environment) at ``si``, seen from ``ref``."""
    return emission_density(scene, mi.DirectionSample3f(scene, si=si, ref=ref), ref, active)


def reflects(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, active: mi.Bool) -> mi.Bool:
    """Whether the surface at ``si`` reflects light (``si.wi`` is overwritten on a copy): a glossy lobe, or a
    non-zero BSDF along the normal. Black emitter surfaces (most area lights) reflect nothing."""
    probe = mi.SurfaceInteraction3f(si)
    probe.wi = mi.Vector3f(0, 0, 1)
    f = bsdf.eval(mi.BSDFContext(), probe, mi.Vector3f(0, 0, 1), active)
    return active & (dr.any(mi.unpolarized_spectrum(f) > 0) | mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy))


#: analytic shapes whose ``sample_position`` gives the point's geometric normal, as a ray hit there would
_EXACT_EMITTER_SHAPES = ("Rectangle", "Disk", "Sphere")


def emitted_point_is_exact(emitter: mi.Emitter) -> bool:
    """Whether an emitter's point of an emitted ray can be taken from ``emitter.sample_position`` instead of a
    ray traced back to it (:class:`SegmentRecorder`): an area light of uniform radiance on a rectangle, disk or
    sphere (a mesh's ``sample_position`` interpolates its vertex normals, and texture coordinates need a hit)
    whose surface reflects nothing (a reflecting one becomes a query, which needs the surface's own frame)."""
    if emitter.class_name() != "AreaLight" or mi.has_flag(emitter.flags(), mi.EmitterFlags.SpatiallyVarying):
        return False
    shape = emitter.get_shape()
    if shape is None or shape.class_name() not in _EXACT_EMITTER_SHAPES:
        return False
    bsdf = shape.bsdf()
    if bsdf is None or bsdf.class_name() != "SmoothDiffuse":
        return False
    if list(mi.traverse(bsdf).keys()) != ["reflectance.value"]:
        return False  # a textured reflectance
    # a constant reflectance: one probe tells (in spectral variants, at wavelengths across the visible range)
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.n, si.sh_frame, si.t = mi.Normal3f(0, 0, 1), mi.Frame3f(mi.Normal3f(0, 0, 1)), 1.0
    if mi.is_spectral:
        si.wavelengths = type(si.wavelengths)(*(400 + 300 * i / max(1, dr.size_v(si.wavelengths) - 1)
                                                for i in range(dr.size_v(si.wavelengths))))
    return not bool(reflects(si, bsdf, mi.Bool(True))[0])


def point_interaction(p: mi.Point3f, n: mi.Normal3f, time: mi.Float, wavelengths) -> mi.Interaction3f:
    """A bare interaction at ``p`` (a reference point for emitter sampling and densities)."""
    it = dr.zeros(mi.Interaction3f, dr.width(p))
    it.p, it.n, it.time = p, n, time
    if wavelengths is not None:
        it.wavelengths = wavelengths
    return it


def emitter_sample_of(pool: SegmentPool) -> mi.DirectionSample3f:
    """The light-side end ``y`` of every segment of ``pool`` as an emitter sample seen from its start ``x``."""
    ds = dr.zeros(mi.DirectionSample3f, pool.size)
    ds.p, ds.n, ds.uv, ds.time = pool.y, pool.ny, pool.emit_uv, pool.surf.time
    ds.d = pool.wx
    ds.dist = dr.norm(pool.y - pool.x)
    ds.emitter = pool.emitter
    return ds


#: the delta emitters whose emitted directions (positions, for directional lights) Mitsuba samples uniformly:
#: the only ones that next-event segments combine with photons (docs/maths.md §3.5)
UNIFORM_DELTA_EMITTERS = ("PointLight", "SpotLight", "DirectionalEmitter")


def delta_emitters(scene: mi.Scene) -> list[tuple[mi.Emitter, float, bool]]:
    """``(emitter, c, positional)`` of every delta emitter of :data:`UNIFORM_DELTA_EMITTERS`: ``c`` is the
    inverse of the density with which ``sample_emitter_ray`` draws its photons' directions (point: ``4π``;
    spot: ``2π (1 - cos θ_cutoff)``), or their positions (directional: ``π R²``, ``R`` the radius of the disc the
    emitter covers the scene with), ``positional`` for the first two."""
    out = []
    for e in scene.emitters():
        if not mi.has_flag(e.flags(), mi.EmitterFlags.Delta):
            continue
        name = emitter_class(e)
        if name == "PointLight":
            out.append((e, 4 * dr.pi, True))
        elif name == "SpotLight":
            cutoff = float(dr.ravel(mi.traverse(e)["cutoff_angle"])[0])
            out.append((e, 2 * dr.pi * (1 - dr.cos(dr.deg2rad(cutoff))), True))
        elif name == "DirectionalEmitter":
            radius = emission_bounds(scene).bounding_sphere().radius
            out.append((e, dr.pi * (radius * (1 + 1500 * 2**-24)) ** 2, False))
    return out


def photon_to_next_event(scene: mi.Scene, emitter: mi.EmitterPtr, x: mi.Point3f, y: mi.Point3f,
                         active: mi.Bool) -> tuple[mi.Float, mi.Bool]:
    """``ρ = d² / p_dir`` (directional lights: ``1 / p_pos``) of the segment from ``x`` to a delta emitter at ``y``:
    the photon weight of its direction over the next-event weight at ``x`` (docs/maths.md §3.5), and where it is
    known (:func:`delta_emitters`)."""
    ratio = dr.zeros(mi.Float, dr.width(active))
    known = dr.zeros(mi.Bool, dr.width(active))
    d2 = dr.squared_norm(x - y)
    for e, c, positional in delta_emitters(scene):
        on = active & (emitter == mi.EmitterPtr(e))
        ratio = dr.select(on, c * d2 if positional else c, ratio)
        known |= on
    return ratio, known


def _arrays(obj) -> list:
    """The Dr.Jit arrays of a (nested) record struct."""
    out = []
    for f in fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, Surface):
            out += _arrays(v)
        elif v is not None and not isinstance(v, int):
            out.append(v)
    return out


def _scatter(target, values, index: mi.UInt32, active: mi.Bool) -> None:
    for f in fields(target):
        t = getattr(target, f.name)
        if isinstance(t, Surface):
            _scatter(t, getattr(values, f.name), index, active)
        elif t is not None and not isinstance(t, int):
            dr.scatter(t, getattr(values, f.name), index, active)


@dataclass
class RecorderLanes:
    """A recorder's per-lane state, carried through the walk's loop."""

    last: mi.UInt32  #: slot of the lane's last record
    last_parent: mi.UInt32  #: parent of ``last``, for segments that absorbed its end
    # light: the first hit, for the emitter's side of the emitted segment, computed after the walk
    first_p: mi.Point3f | None = None
    first_n: mi.Normal3f | None = None


def read_packed(flat: mi.Float, packets: int, layout: list, names, index: mi.UInt32,
                active: mi.Bool | bool = True) -> dict:
    """Fields ``names`` of entries ``index`` of an array of records of ``packets`` packets each, laid out as
    ``layout`` (:attr:`RecordBuffer.layout`; the names of :data:`RecordBuffer.FLAGS` read their bit of
    ``flags``): one packet gather per packet that holds any of them."""
    size = RecordBuffer.PACKET
    wanted = {"flags" if name in RecordBuffer.FLAGS else name for name in names}
    entries = [entry for entry in layout if entry[0] in wanted]
    loaded = {}
    for _, _, first, count in entries:
        for k in range(first // size, (first + count - 1) // size + 1):
            if k not in loaded:
                loaded[k] = dr.gather(mi.ArrayXf, flat, index * packets + k, active, shape=(size, dr.width(index)))
    raw = {}
    for name, tp, first, count in entries:
        parts = [loaded[c // size][c % size] for c in range(first, first + count)]
        if dr.depth_v(tp) > 1:
            raw[name] = tp(*parts)
        else:
            # pointers (shapes, emitters) are u32 registry ids, and come back through u32
            raw[name] = parts[0] if tp is mi.Float else dr.reinterpret_array(
                tp, parts[0] if tp is mi.UInt32 else dr.reinterpret_array(mi.UInt32, parts[0]))
    return {name: (raw["flags"] & (1 << RecordBuffer.FLAGS.index(name))) != 0 if name in RecordBuffer.FLAGS
            else raw[name] for name in names}


def read_surfaces(flat: mi.Float, packets: int, layout: list, shapes: mi.ShapePtr | None, index: mi.UInt32,
                  active: mi.Bool | bool = True) -> Surface:
    """The walk surfaces of entries ``index`` of an array of records (:func:`read_packed`), their shapes from
    ``shapes`` (or, None, from the records)."""
    names = [f"surf.{f.name}" for f in fields(Surface) if f.name != "shape" or shapes is None]
    names = [name for name in names if name != "surf.wavelengths" or mi.is_spectral]
    values = read_packed(flat, packets, layout, names, index, active)
    if shapes is not None:
        values["surf.shape"] = dr.gather(mi.ShapePtr, shapes, index, active)
    return Surface(wavelengths=values.get("surf.wavelengths"),
                   **{name[5:]: v for name, v in values.items() if name != "surf.wavelengths"})


class RecordBuffer:
    """The segments of one pool, in pool layout (camera orientation), in preallocated arrays: the camera
    walk's first, then the light walk's.

    A recording lane claims its slot with an atomic counter (``dr.scatter_inc``) and scatters its segment
    there from inside the walk's kernel, and :meth:`SegmentPool.build` reads the pool from the first slots.
    The slots of one bounce are in no fixed order, so nothing may depend on it (random numbers drawn per
    segment are keyed by sample and segment index). Before each loop of a walk the arrays are made large
    enough for what it can record (one copy when they grow).

    Each scattered value costs, so the recorders write what cannot be derived later, and a walk's records write
    only :data:`PACKED` (the boolean fields as the bits of one word among them), to one array of records,
    ``core``, as packets of eight floats: a lane stores a packet at once where it would store each value on its
    own, and a masked scatter of a field few records carry costs every lane of the walk's kernel
    (docs/maths.md §3.3). :meth:`SegmentPool.build` unpacks them and adds what is rare: the emission of the
    records that end on an emitter."""

    #: fields a recorder does not write: :meth:`SegmentPool.build` derives them from the others
    DERIVED = frozenset({"kind", "x_surf", "y_surf"})
    #: fields written only where a segment carries emission, that is where its ``emitter`` (always written) is
    #: not None, after the walks (:meth:`SegmentPool.build`, :meth:`SegmentRecorder.finish`) or by next-event
    #: records; :meth:`SegmentPool.build` reads them as zero elsewhere. Zeroing them over the whole capacity
    #: instead (eight slots per lane reserved, about 40% used) took a third of a pool's trace.
    EMISSION = frozenset({"le", "emit_factor", "delta_emit", "emit_uv"})
    #: the boolean fields (``surf.`` those of the arrival surface), as bits of the ``flags`` word
    FLAGS = ("private", "attempt", "straight", "absorbed", "sharp", "delta_emit", "surf.valid", "surf.smooth")
    #: what every record writes, in ``core`` (u32 fields, and the shape and emitter pointers as their u32 ids, as
    #: their bits), in this order: the surface's point,
    #: normal and coordinates share the first packet, its frame, time and the flags the second (the surface
    #: fields fill the first packets, which :meth:`SegmentPool.walk_surface` reads at random); ``origin`` is
    #: where the walk's segment started (x of camera and next-event segments, y of light segments)
    PACKED = ("surf.p", "surf.n", "surf.uv", "surf.s", "surf.sn", "surf.time", "flags", "surf.wavelengths", "dy",
              "lead", "q", "pdf", "parent", "index", "pixel", "depth", "surf.shape", "emitter", "wx", "chain",
              "origin")
    PACKET = 8  #: floats per packet

    def __init__(self, capacity: int):
        self.capacity = max(int(capacity), 1)
        proto = SegmentPool.prototype()
        for name in self.FLAGS:
            _set(proto, name, None)
        #: (name, type, first component, components) of the packed fields
        self.layout, offset = [], 0
        for name in self.PACKED:
            if name in ("flags", "origin"):
                tp = mi.UInt32 if name == "flags" else mi.Point3f
            else:
                tp = type(_get(proto, name)) if _get(proto, name) is not None else None
            if tp is None:
                continue  # wavelengths outside spectral variants
            count = 1 if dr.depth_v(tp) == 1 else dr.size_v(tp)  # a mono Spectrum is a vector of one
            self.layout.append((name, tp, offset, count))
            offset += count
            if name not in ("flags", "origin"):
                _set(proto, name, None)
        self.packets = -(-offset // self.PACKET)
        #: the layout of the surface fields (and the flags, which hold ``valid`` and ``smooth``), and the packets
        #: they fill
        self.surface_layout = [e for e in self.layout if (e[0].startswith("surf.") and e[0] != "surf.shape")
                               or e[0] == "flags"]
        self.surface_packets = -(-max(first + count for _, _, first, count in self.surface_layout) // self.PACKET)
        self.data = _map(proto, lambda v: dr.empty(type(v), self.capacity))
        self.core = dr.empty(mi.Float, self.capacity * self.packets * self.PACKET)
        dr.make_opaque(*_arrays(self.data), self.core)
        self.counter = dr.zeros(mi.UInt32, 1)
        dr.make_opaque(self.counter)

    def count(self) -> int:
        """Slots claimed so far (evaluates what is pending)."""
        return int(self.counter[0])

    def reserve(self, records: int) -> None:
        """Room for ``records`` more (outside any loop)."""
        count = self.count()
        if count + records > self.capacity:
            capacity = max(2 * self.capacity, count + records)
            keep = dr.arange(mi.UInt32, capacity)
            active = keep < dr.opaque(mi.UInt32, count)
            self.data = _gather(self.data, keep, active)
            words = dr.arange(mi.UInt32, capacity * self.packets * self.PACKET)
            self.core = dr.gather(mi.Float, self.core, words,
                                  words < dr.opaque(mi.UInt32, count * self.packets * self.PACKET))
            dr.eval(*_arrays(self.data), self.core)
            self.capacity = capacity

    def claim(self, active: mi.Bool) -> mi.UInt32:
        """One slot for each ``active`` lane (room for it was reserved)."""
        return dr.scatter_inc(self.counter, mi.UInt32(0), active)

    def write(self, segment: SegmentPool, origin: mi.Point3f, slot: mi.UInt32, active: mi.Bool,
              emission: mi.Bool | None = None, skip: frozenset = frozenset()) -> None:
        """Scatter ``segment`` (and ``origin``, see :data:`PACKED`) to ``slot``: the packed fields, the others
        but the derived ones and ``skip`` only with an ``emission`` mask (next-event records, outside a walk),
        the emission fields only where it is set."""
        assert not set(skip) & set(self.PACKED), "every record writes the packed fields"
        flags = mi.UInt32(0)
        for bit, name in enumerate(self.FLAGS):
            flags |= dr.select(_get(segment, name), mi.UInt32(1 << bit), 0)
        words = []
        for name, tp, _, count in self.layout:
            value = flags if name == "flags" else (origin if name == "origin" else _get(segment, name))
            if dr.depth_v(tp) > 1:
                words += [value[i] for i in range(count)]
            else:
                words.append(value if tp is mi.Float else dr.reinterpret_array(
                    mi.Float, mi.UInt32(value) if tp is mi.UInt32 else dr.reinterpret_array(mi.UInt32, value)))
        words += [mi.Float(0)] * (self.packets * self.PACKET - len(words))
        if not dr.flag(dr.JitFlag.SymbolicScope):
            # outside a loop a packet scatter evaluates its index, and a claimed slot (scatter_inc) evaluates once
            dr.eval(slot)
        base = slot * self.packets
        for k in range(self.packets):
            dr.scatter(self.core, mi.ArrayXf(*words[k * self.PACKET:(k + 1) * self.PACKET]), base + k, active)
        if emission is None:
            return
        for f in fields(self.data):
            if f.name in self.DERIVED or f.name in skip:
                continue
            t = getattr(self.data, f.name)
            mask = active & emission if f.name in self.EMISSION else active
            if isinstance(t, Surface):
                _scatter(t, getattr(segment, f.name), slot, mask)
            elif t is not None and not isinstance(t, int):
                dr.scatter(t, getattr(segment, f.name), slot, mask)

    def read(self, names, index: mi.UInt32, active: mi.Bool | bool = True) -> dict:
        """The packed fields ``names`` (of :data:`PACKED`, or of :data:`FLAGS`) of the records ``index``: one
        packet gather per packet that holds any of them."""
        return read_packed(self.core, self.packets, self.layout, names, index, active)

    def surfaces(self, index: mi.UInt32, active: mi.Bool | bool = True) -> Surface:
        """The walk surfaces of the records ``index``."""
        return read_surfaces(self.core, self.packets, self.layout, None, index, active)

    def slice(self, start: int, stop: int, name: str):
        """Field ``name`` of slots ``start .. stop - 1`` (lazy gather)."""
        index = dr.arange(mi.UInt32, stop - start) + dr.opaque(mi.UInt32, start)
        if name == "surf":
            return self.surfaces(index)
        if name in self.FLAGS or any(name == entry[0] for entry in self.layout):
            return self.read([name], index)[name]
        v = getattr(self.data, name)
        return dr.gather(type(v), v, index)


class SegmentRecorder:
    """Writes the segments of one walk into a ``RecordBuffer``: the consumer that
    ``RandomWalk.run_symbolic`` traces into its loop body.

    Each segment is kept with the walk vertex it *arrives* at (``surf``: its end ``y`` for camera segments,
    its start ``x`` for light segments, which run from the light side in walk order), in camera orientation."""

    def __init__(self, scene: mi.Scene, kind: int, n: int, buffer: RecordBuffer,
                 emitter: mi.EmitterPtr | None = None, emitted_weight: mi.Spectrum | None = None,
                 emitted_at: tuple[mi.Ray3f, mi.Point2f] | None = None):
        """Light walks: ``emitter`` and ``emitted_weight`` of each lane's emitted ray, and ``emitted_at``, that
        ray and the spatial sample ``scene.sample_emitter_ray`` drew it with."""
        self.scene, self.kind, self.n, self.buffer = scene, kind, n, buffer
        self.start = buffer.count()  #: the first slot of this walk's records
        self.lanes = dr.arange(mi.UInt32, n)
        #: light, after the walk: (slot, emitter surface) of the emitted segments whose emitter reflects light
        self.reflecting: tuple[mi.UInt32, Surface] | None = None
        if kind == LIGHT:
            self.delta = mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
            self.emitted_weight = emitted_weight
            self.emitter = emitter
            self.emitted_ray, self.emitted_sample = emitted_at
            # read by the walk and gathered after it: one kernel for them
            dr.eval(self.delta, self.emitted_weight, self.emitter, self.emitted_ray, self.emitted_sample)

    def initial(self) -> RecorderLanes:
        n = self.n
        lanes = RecorderLanes(last=dr.full(mi.UInt32, INVALID, n), last_parent=dr.full(mi.UInt32, INVALID, n))
        if self.kind == LIGHT:
            lanes.first_p, lanes.first_n = dr.zeros(mi.Point3f, n), dr.zeros(mi.Normal3f, n)
        return lanes

    def reserve(self, vertices: int) -> None:
        """Before a walk loop of up to ``vertices`` vertices: one record per lane and vertex at most."""
        self.buffer.reserve(self.n * vertices)

    def finish(self, lanes: RecorderLanes) -> None:
        if self.kind == LIGHT:
            self._emitter_side(lanes)

    def _emitter_side(self, lanes: RecorderLanes) -> None:
        """Light, after the walk: the emitter's side of each emitted segment (docs/maths.md §3.3), written to
        its record. Its radiance toward the first hit, its normal, texture coordinates and the emission
        technique's density, at the emitted point: taken again from the shape where that is exact
        (:func:`emitted_point_is_exact`), else found by a ray traced back from the first hit. Computed once
        per walk, outside the walk's loop, whose every iteration would otherwise pay these calls."""
        scene, buffer = self.scene, self.buffer
        # the records of emitted segments (a fraction of the lanes where most emitted rays leave the scene; a
        # lane has two where its emitted segment went on through a mixed vertex's delta lobe, docs/maths.md §2.3)
        stop = buffer.count()
        if stop == self.start:
            return
        records = dr.arange(mi.UInt32, stop - self.start) + dr.opaque(mi.UInt32, self.start)
        read = buffer.read(["index", "pixel"], records)
        first = read["index"] == 0
        delta = dr.gather(mi.Bool, self.delta, read["pixel"], first)
        if any(mi.has_flag(e.flags(), mi.EmitterFlags.Delta) for e in scene.emitters()):
            # a delta emitter's emitted segment: its ray's weight, a normal of 0 (no surface, docs/maths.md §3.3)
            data = buffer.data
            dr.scatter(data.le, dr.gather(mi.Spectrum, self.emitted_weight, read["pixel"], delta), records, delta)
            dr.scatter(data.emit_factor, 0.0, records, delta)
            dr.scatter(data.ny, mi.Normal3f(0), records, delta)
            dr.scatter(data.emit_uv, mi.Point2f(0), records, delta)
            dr.eval(data.le, data.emit_factor, data.ny, data.emit_uv)
        index = dr.compress(first & ~delta)
        n = dr.width(index)
        if n == 0:
            return
        slot = dr.gather(mi.UInt32, records, index)
        lane = dr.gather(mi.UInt32, read["pixel"], index)
        ray = dr.gather(mi.Ray3f, self.emitted_ray, lane)
        emitter = dr.gather(mi.EmitterPtr, self.emitter, lane)
        active = dr.full(mi.Bool, True, n)
        hit = dr.zeros(mi.SurfaceInteraction3f, n)
        hit.p = dr.gather(mi.Point3f, lanes.first_p, lane)
        hit.n = dr.gather(mi.Normal3f, lanes.first_n, lane)
        hit.time, hit.wavelengths = ray.time, ray.wavelengths
        exact = dr.zeros(mi.Bool, n)
        emitters = scene.emitters()
        exact_point = [emitted_point_is_exact(e) for e in emitters]  # one probe each, past the early returns
        for e, is_exact in zip(emitters, exact_point, strict=True):
            if is_exact:
                exact |= emitter == mi.EmitterPtr(e)
        # where every emitter's point is exact, infinite or delta, no lane traces back to it
        point_known = [is_exact or mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)
                       or mi.has_flag(e.flags(), mi.EmitterFlags.Delta)
                       for e, is_exact in zip(emitters, exact_point, strict=True)]
        traced = ~exact
        infinite = None
        if any(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) and not mi.has_flag(
                e.flags(), mi.EmitterFlags.Delta) for e in scene.emitters()):
            # a ray traced back from an environment's first hit leaves the scene (the emitted ray came from
            # outside it, unblocked): what it would find is known without tracing it
            infinite = mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite)
            traced &= ~infinite
        if not all(point_known):
            si_e = scene.ray_intersect(hit.spawn_ray(-ray.d), traced)
        else:
            si_e = dr.zeros(mi.SurfaceInteraction3f, n)  # no emitter's point needs the ray: not even traced
        if infinite is not None:
            # a miss: no surface, and the environment's radiance arriving back along the emitted ray
            far = dr.zeros(mi.SurfaceInteraction3f, n)
            far.t, far.wi, far.time = dr.full(mi.Float, dr.inf, n), ray.d, ray.time
            if mi.is_spectral:
                far.wavelengths = ray.wavelengths
            si_e = dr.select(infinite, far, si_e)
        if any(e.get_shape() is not None and not mi.has_flag(e.flags(), mi.EmitterFlags.Delta)
               for e in scene.emitters()):
            # Area lights take the emitted point from the shape with the spatial sample (sample_ray does the
            # same): that point again where it is exact, and where the ray traced back from the first hit
            # misses the emitter (grazing, or a small shape)
            shape = emitter.get_shape()
            area = ~mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite) & (
                shape != None)  # noqa: E711 (Dr.Jit pointer test)
            emitted, _ = emitter.sample_position(ray.time, dr.gather(mi.Point2f, self.emitted_sample, lane), area)
            missed = traced & area & ~(si_e.is_valid() & (si_e.shape == shape))
            on_shape = dr.zeros(mi.SurfaceInteraction3f, n)
            on_shape.p, on_shape.n, on_shape.uv, on_shape.time = emitted.p, emitted.n, emitted.uv, ray.time
            if mi.is_spectral:
                on_shape.wavelengths = ray.wavelengths
            on_shape.shape = shape
            on_shape.sh_frame = mi.Frame3f(emitted.n)
            on_shape.wi = on_shape.to_local(ray.d)  # toward the first hit, as the traced-back ray arrives there
            on_shape.t = dr.norm(hit.p - emitted.p)
            si_e = dr.select(active & (exact | missed), on_shape, si_e)
        ref = dr.zeros(mi.Interaction3f, n)
        ref.p, ref.n, ref.time, ref.wavelengths = hit.p, hit.n, ray.time, ray.wavelengths
        em = si_e.emitter(scene)
        bsdf_e = si_e.bsdf()
        here = Surface.of(si_e, bsdf_e)
        # black emitter surfaces (most area lights) reflect nothing: no query there
        here.smooth &= reflects(si_e, bsdf_e, active)
        data = buffer.data
        dr.scatter(data.le, em.eval(si_e, active), slot, active)
        dr.scatter(data.emit_factor, _emission_factor(scene, si_e, ref, active), slot, active)
        dr.scatter(data.ny, si_e.n, slot, active)
        dr.scatter(data.emit_uv, si_e.uv, slot, active)
        dr.eval(*_arrays(here))  # with the scatters, in one kernel
        reflecting = dr.compress(here.smooth)
        if dr.width(reflecting):
            self.reflecting = (dr.gather(mi.UInt32, slot, reflecting), _gather(here, reflecting))

    def visit(self, v: Vertex, lanes: RecorderLanes) -> RecorderLanes:
        scene, si = self.scene, v.si
        record = v.ends_segment & ~v.dropped
        if self.kind == LIGHT:
            record &= si.is_valid()  # an escaped light segment starts nowhere
        seg = v.segment
        sharp = seg.sharp & (self.kind == CAMERA)
        # a segment that absorbed the end of the last one (docs/maths.md §2.3) starts where that one started
        parent = dr.select(seg.absorbed, lanes.last_parent, lanes.last)
        slot = self.buffer.claim(record)
        # A walk writes the packed fields alone (RecordBuffer.PACKED): the arrival end is the walk surface
        # (``surf``), the other end (x of a camera segment, y of a light segment) the origin, with the normal of
        # the parent's arrival, and the emission fields are the build's and finish()'s to add (None here)
        if self.kind == CAMERA:
            delta_emit = dr.zeros(mi.Bool, self.n)
            emitter = si.emitter(scene)  # an environment's where the ray escaped
            wx, dy = seg.direction, -v.ray.d  # x toward y, y toward x
        else:
            first_seg = seg.index == 0
            delta_emit = first_seg & self.delta
            emitter = dr.select(first_seg, self.emitter, mi.EmitterPtr(None))
            wx, dy = -v.ray.d, seg.direction
        segment = SegmentPool(
            surf=Surface.of(si, v.bsdf), kind=None, x=None, nx=None, wx=wx, y=None, ny=None, dy=dy, x_surf=None,
            y_surf=None, chain=seg.chain, lead=seg.lead, private=seg.private, parent=parent, index=seg.index,
            attempt=v.continues, q=v.q, le=None, emit_factor=None, delta_emit=delta_emit, pixel=self.lanes,
            pdf=seg.pdf, straight=seg.straight, absorbed=seg.absorbed, sharp=sharp, depth=v.depth, emitter=emitter,
            emit_uv=None, camera_count=0, light_count=0,
        )
        self.buffer.write(segment, seg.origin, slot, record)
        # a dropped segment is not kept, but the one that absorbs its end starts where it started, from its parent
        out = RecorderLanes(last=dr.select(record, slot, lanes.last),
                            last_parent=dr.select(record | v.dropped, parent, lanes.last_parent))
        if self.kind == LIGHT:
            hit = v.active & (v.depth == 1)
            out.first_p = dr.select(hit, si.p, lanes.first_p)
            out.first_n = dr.select(hit, si.n, lanes.first_n)
        return out

    def emitter_surfaces(self) -> tuple[mi.UInt32, Surface] | None:
        """Light, after the walk: (slot, emitter surface) of the first segments whose emitter reflects light."""
        return self.reflecting


def technique_records(attempt: mi.Bool, surf: Surface, glossy: mi.Bool | None = None) -> mi.Bool:
    """The records whose arrival is a technique (docs/maths.md §3): the walk attempted to continue from a vertex
    with a non-delta lobe that is not a private glossy one (``glossy``: the records arriving at one, or None).
    A camera one is also a next-event technique (§3.5)."""
    tech = attempt & surf.smooth
    return tech if glossy is None else tech & ~glossy


def record_next_event(scene: mi.Scene, buffer: RecordBuffer, camera_count: int, seed: int,
                      private_glossy: bool = False, every_delta: bool = False) -> int:
    """One emitter sample (``scene.sample_emitter_direction``, visibility tested) from the end of every camera
    record that is a technique (:func:`technique_records`), kept as a segment of the pool where it
    reached an emitter that does not reflect (docs/maths.md §3.5); appended to ``buffer``. Area, textured and
    environment emitters: its ``le`` is the emitted radiance; delta emitters of :data:`UNIFORM_DELTA_EMITTERS`:
    the sample's weight; ``every_delta`` (pools without light sub-paths, where no photon competes with them):
    every delta emitter's (a projector's too). Returns the number of records written."""
    nc = camera_count
    if nc == 0 or not scene.emitters():
        return 0
    buffer.reserve(nc)
    start = buffer.count()
    segment, ok = _next_event_segments(scene, buffer, nc, seed, private_glossy, every_delta)
    slot = buffer.claim(ok)
    buffer.write(segment, segment.x, slot, ok, ok, frozenset({"x", "nx"}))  # nx: the parent's, derived at build
    return buffer.count() - start


def _next_event_segments(scene: mi.Scene, buffer: RecordBuffer, nc: int, seed: int,
                         private_glossy: bool, every_delta: bool = False) -> tuple[SegmentPool, mi.Bool]:
    """The next-event segments of :func:`record_next_event` and where they are kept, evaluated: once no pending
    gather reads the buffer, scattering into it does not copy its arrays (Dr.Jit copies a scatter target that
    other variables still reference: 25 arrays of the buffer's whole capacity, half a pool's trace)."""
    surf = buffer.slice(0, nc, "surf")
    attempt, dy = buffer.slice(0, nc, "attempt"), buffer.slice(0, nc, "dy")
    index, pixel, depth = buffer.slice(0, nc, "index"), buffer.slice(0, nc, "pixel"), buffer.slice(0, nc, "depth")
    dr.eval(*_arrays(surf), attempt, dy, index, pixel, depth)
    glossy = None
    if private_glossy:
        from .samplers.walk import glossy_vertex

        glossy = surf.valid & glossy_vertex(surf.shape.bsdf())
    tech = technique_records(attempt, surf, glossy)
    si = surf.interaction(dy)
    state = ((seed & 0xFFFFFFFF) * 0x9E3779B97F4A7C15 + 0x61C88647) & 0xFFFFFFFFFFFFFFFF
    rng = mi.PCG32()  # one stream per (camera sample, segment index), as the pool's other per-segment numbers
    rng.seed(dr.opaque(mi.UInt64, state), (mi.UInt64(index) << 32) | mi.UInt64(pixel))
    ds, weight = scene.sample_emitter_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()), True, tech)
    emitter = ds.emitter
    delta = mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
    ok = tech & (ds.pdf > 0) & dr.any(mi.unpolarized_spectrum(weight) != 0) & (emitter != None)  # noqa: E711
    if not every_delta:  # the photons of a delta emitter without a known density would have no D (§3.5)
        _, uniform = photon_to_next_event(scene, emitter, si.p, ds.p, ok & delta)
        ok &= ~delta | uniform
    # an emitter surface that reflects: the pool's other techniques carry what leaves it, emission included
    shape = emitter.get_shape()
    has_shape = ok & ~delta & (shape != None)  # noqa: E711
    si_e = dr.zeros(mi.SurfaceInteraction3f, nc)
    si_e.p, si_e.n, si_e.uv, si_e.shape, si_e.time = ds.p, ds.n, ds.uv, shape, si.time
    si_e.sh_frame = mi.Frame3f(ds.n)
    if mi.is_spectral:
        si_e.wavelengths = si.wavelengths
    ok &= ~reflects(si_e, shape.bsdf(), has_shape)
    ref = point_interaction(si.p, si.n, si.time, si.wavelengths if mi.is_spectral else None)
    # no walk surface at the emitter (not a query): only the pool's wavelengths and the sample's time
    blank = _map(SegmentPool.prototype().surf, lambda v: dr.zeros(type(v), nc))
    blank.time, blank.wavelengths = surf.time, surf.wavelengths
    parent = dr.arange(mi.UInt32, nc)
    segment = SegmentPool(
        surf=blank, kind=dr.full(mi.UInt32, NEXT_EVENT, nc), x=si.p, nx=si.n, wx=ds.d, y=ds.p, ny=ds.n, dy=-ds.d,
        x_surf=parent, y_surf=dr.full(mi.UInt32, INVALID, nc), chain=mi.Spectrum(1), lead=mi.Spectrum(1),
        private=dr.zeros(mi.Bool, nc), parent=parent, index=index + 1, attempt=dr.zeros(mi.Bool, nc),
        q=dr.zeros(mi.Float, nc), le=dr.select(delta, weight, weight * ds.pdf),
        emit_factor=emission_density(scene, ds, ref, ok & ~delta), delta_emit=delta, pixel=pixel, pdf=ds.pdf,
        straight=dr.full(mi.Bool, True, nc), absorbed=dr.zeros(mi.Bool, nc), sharp=dr.zeros(mi.Bool, nc),
        depth=depth + 1, emitter=emitter, emit_uv=ds.uv, camera_count=0, light_count=0)
    dr.eval(*_arrays(segment), ok)
    return segment, ok


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
    absorbed: mi.Bool  #: through the delta lobe of a mixed vertex, absorbed: no camera technique produces it
    sharp: mi.Bool
    depth: mi.UInt32
    emitter: mi.EmitterPtr  #: the emitter at ``y`` (None where ``y`` emits nothing)
    emit_uv: mi.Point2f  #: surface coordinates there
    camera_count: int
    light_count: int
    #: emitter surfaces of first light segments (``y_surf`` >= ``size`` indexes them), or None
    emitter_surf: Surface | None = None
    #: next-event segments, after the light segments (docs/maths.md §3.5)
    next_event_count: int = 0
    #: the walk surfaces again, in the records of ``surf_layout[0]`` packets they were written to
    #: (:attr:`RecordBuffer.core`, first packets): a random read of a surface is then one load per packet, not one
    #: cache miss per value
    surf_packed: mi.Float | None = None
    surf_layout: tuple | None = None

    @property
    def size(self) -> int:
        return self.camera_count + self.light_count + self.next_event_count

    @staticmethod
    def prototype() -> SegmentPool:
        """A pool of empty arrays: the field types."""
        f, u, b = mi.Float, mi.UInt32, mi.Bool
        wavelengths = type(dr.zeros(mi.SurfaceInteraction3f).wavelengths)() if mi.is_spectral else None
        surf = Surface(p=mi.Point3f(), n=mi.Normal3f(), s=mi.Vector3f(), sn=mi.Normal3f(),
                       uv=mi.Point2f(), shape=mi.ShapePtr(), time=f(), wavelengths=wavelengths, valid=b(), smooth=b())
        return SegmentPool(
            surf=surf, kind=u(), x=mi.Point3f(), nx=mi.Normal3f(), wx=mi.Vector3f(), y=mi.Point3f(),
            ny=mi.Normal3f(), dy=mi.Vector3f(), x_surf=u(), y_surf=u(), chain=mi.Spectrum(), lead=mi.Spectrum(),
            private=b(), parent=u(), index=u(), attempt=b(), q=f(), le=mi.Spectrum(), emit_factor=f(),
            delta_emit=b(), pixel=u(), pdf=f(), straight=b(), absorbed=b(), sharp=b(), depth=u(),
            emitter=mi.EmitterPtr(), emit_uv=mi.Point2f(), camera_count=0, light_count=0)

    @staticmethod
    def build(scene: mi.Scene, buffer: RecordBuffer, camera_count: int, light_count: int,
              emitter_surfaces: tuple[mi.UInt32, Surface] | None = None,
              next_event_count: int = 0) -> SegmentPool:
        """The pool of the first ``camera_count`` (camera), the next ``light_count`` (light) and the next
        ``next_event_count`` (next-event, :func:`record_next_event`) segments of ``buffer``: views of its arrays,
        the packed fields unpacked, and the derived fields; a segment's index is its slot.
        ``emitter_surfaces``: (slot, surface) of the first light segments whose emitter reflects
        (:meth:`SegmentRecorder.emitter_surfaces`); they become queries at the emitter (their ``y``)."""
        nc, nl, ne = camera_count, light_count, next_event_count
        data = buffer.data
        # The packed fields (RecordBuffer.PACKED, the boolean ones from their word) and what the recorders did not
        # write (RecordBuffer.DERIVED, and each segment's arrival end: its walk surface), in one kernel over the
        # pool's slots. The origin of a segment is its x (camera and next-event segments) or its y (light
        # segments); the normal there is its parent's arrival's (0 at the sensor; a first light segment's, and a
        # next-event segment's y, were written).
        n = nc + nl + ne
        idx = dr.arange(mi.UInt32, n)
        cam = idx < dr.opaque(mi.UInt32, nc)
        nee = idx >= dr.opaque(mi.UInt32, nc + nl)
        light = ~cam & ~nee
        packed = buffer.read([name for name, *_ in buffer.layout if name != "flags"] + list(RecordBuffer.FLAGS),
                             idx)
        derived = dict(packed)
        origin = derived.pop("origin")
        parent, p, nrm = packed["parent"], packed["surf.p"], packed["surf.n"]
        later = packed["index"] > 0
        from_parent = (cam & later) | nee | (light & later)
        pn = buffer.read(["surf.n"], parent, from_parent)["surf.n"]
        written_ny = nee | (light & ~later)
        derived.update({
            "kind": dr.select(cam, mi.UInt32(CAMERA), dr.select(nee, mi.UInt32(NEXT_EVENT), mi.UInt32(LIGHT))),
            "x_surf": dr.select(light, idx, parent),
            "y_surf": dr.select(cam, idx, dr.select(nee, INVALID, parent)),
            "x": dr.select(light, p, origin),
            "nx": dr.select(light, nrm, dr.select(cam & ~later, mi.Normal3f(0), pn)),
            "y": dr.select(cam, p, dr.select(light, origin, dr.gather(mi.Point3f, data.y, idx, nee))),
            "ny": dr.select(cam, nrm, dr.select(written_ny, dr.gather(mi.Normal3f, data.ny, idx, written_ny), pn)),
        })
        # Camera segments that end on an emitter (or escape to an environment) carry its emission, and the
        # emission technique's density along their last ray (docs/maths.md §3.3), evaluated here, where a masked lane
        # costs little, and not in the walk, where each emission field cost every lane a scatter
        surf = Surface(**{f.name: packed.get(f"surf.{f.name}") for f in fields(Surface)})
        si = surf.interaction(packed["dy"])
        em = packed["emitter"]
        cam_emits = cam & (em != None)  # noqa: E711 (Dr.Jit pointer test)
        # the density depends on the arriving ray's direction alone (a point one unit back along it): that of
        # an emitter's texture or of an environment (§3.3)
        ref = point_interaction(p + packed["dy"], nrm, surf.time, surf.wavelengths)
        camera_emission = {"le": em.eval(si, cam_emits),
                           "emit_factor": _emission_factor(scene, si, ref, cam_emits & later),
                           "emit_uv": surf.uv}
        dr.eval(*derived.values(), camera_emission["le"], camera_emission["emit_factor"])
        if nl:
            # Light segments whose y lies on an emitter (light that bounced back onto one) carry its emission
            # (never a delta emitter's: their delta_emit, written, stays False) ...
            slots = dr.arange(mi.UInt32, nl) + dr.opaque(mi.UInt32, nc)
            y_surf = dr.gather(mi.UInt32, derived["parent"], slots)  # a light segment's y is its parent's arrival
            has_y = y_surf != INVALID  # before the emitter surfaces join: walk surfaces only
            ys = buffer.surfaces(y_surf, has_y)
            si_y = ys.interaction(dr.gather(mi.Vector3f, derived["dy"], slots))
            em = si_y.shape.emitter()
            lit = has_y & ys.valid & (em != None)  # noqa: E711 (Dr.Jit pointer test)
            dr.scatter(data.le, em.eval(si_y, lit), slots, lit)
            dr.scatter(derived["emitter"], em, slots, lit)
            dr.scatter(data.emit_uv, ys.uv, slots, lit)
            # ... and the emission technique could have produced them too: it belongs in their denominator.
            ref = dr.zeros(mi.Interaction3f, nl)
            ref.p = dr.gather(mi.Point3f, derived["surf.p"], slots)  # its x, the walk's arrival
            dr.scatter(data.emit_factor, _emission_factor(scene, si_y, ref, lit), slots, lit)
            dr.eval(data.le, derived["emitter"], data.emit_uv, data.emit_factor)
            if emitter_surfaces is not None:
                at, surfaces = emitter_surfaces
                dr.scatter(derived["y_surf"], dr.arange(mi.UInt32, dr.width(at)) + dr.opaque(mi.UInt32, n), at)
                dr.eval(derived["y_surf"])
        # the emission fields where the segment's y emits (RecordBuffer.EMISSION), zero elsewhere
        emits = derived["emitter"] != None  # noqa: E711 (Dr.Jit pointer test)
        written = emits & ~cam
        for name in RecordBuffer.EMISSION:
            field = getattr(data, name)
            derived[name] = (derived[name] & emits if field is None else dr.select(
                emits, dr.select(cam, camera_emission[name], dr.gather(type(field), field, idx, written)),
                dr.zeros(type(field), 1)))
        dr.eval(*(derived[name] for name in RecordBuffer.EMISSION))
        pool = _map(data, lambda v: dr.reshape(type(v), v, n, shrink=True))
        for name, value in derived.items():
            current = _get(pool, name)
            _set(pool, name, value if current is None else type(current)(value))
        pool.camera_count, pool.light_count, pool.next_event_count = nc, nl, ne
        # random reads of a surface (end_surface) read the buffer's records: its packets share one cache line
        pool.surf_packed = buffer.core
        pool.surf_layout = (buffer.packets, buffer.surface_layout)
        if nl and emitter_surfaces is not None:
            pool.emitter_surf = emitter_surfaces[1]
        return pool

    def walk_surface(self, index: mi.UInt32, active: mi.Bool | bool = True) -> Surface:
        """``surf`` of the segments ``index``, read at random from the packed copy (pools of :meth:`build`)."""
        packets, layout = self.surf_layout
        return read_surfaces(self.surf_packed, packets, layout, self.surf.shape, index, active)

    def end_surface(self, which: str, index: mi.UInt32, active: mi.Bool) -> Surface:
        ref = self.x_surf if which == "x" else self.y_surf
        s = dr.gather(mi.UInt32, ref, index, active)
        size = dr.opaque(mi.UInt32, self.size)  # opaque: the pool's size must not be a kernel constant
        walk = self.walk_surface(s, active & (s < size))
        if self.emitter_surf is None or which == "x":
            return walk
        on_emitter = active & (s != INVALID) & (s >= size)
        emitter = _gather(self.emitter_surf, s - size, on_emitter)
        return _select(on_emitter, emitter, walk)
