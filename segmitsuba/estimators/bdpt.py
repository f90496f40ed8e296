r"""MIS over segment-sampling techniques: segment BDPT (talk: "BDPT = camera/light segment sampler + bridge
segment sampler + multiple sampling techniques").

A path of ``k`` (generalized) segments ``s_1 .. s_k`` runs from the sensor ``v_0`` through segment vertices
``v_1 .. v_{k-1}`` to an emitter ``v_k``. Technique ``c`` (1 <= c <= k+1) samples ``s_1 .. s_{c-1}`` with the
camera sampler, ``s_{c+1} .. s_k`` with the light sampler and makes ``s_c`` a bridge: ``c = 1`` is light
tracing (bridge to the sensor), ``c = k`` emitter sampling (bridge to a point sampled on an emitter; it
replaces the light sub-path's own first vertex, as in SmallVCM's BDPT), ``c = k + 1`` the camera sampler
hitting the emitter. A bridge must be straight and join two non-delta vertices; other techniques are void.

Balance-heuristic weights compare the techniques' densities in the product-area measure. Divided by the
product of every segment's (generalized) geometry term ``G_i``, which is common to all techniques, the density
of technique ``c`` is

    P_c = A_{c-1} B_{c+1} / G_c,   A_j = prod_{i<=j} a_i,   B_j = (prod_{i>=j} b_i) E,

with ``a_i = p(s_i | camera side) / cos`` at ``v_{i-1}`` (solid-angle density of the segment's first direction
over the cosine there; ``a_1`` the sensor's solid-angle density of its ray), ``b_i`` the same for the light
sampler at ``v_i`` (adjoint BSDF), and ``E`` the emission density at ``v_k`` divided by its cosine (the
filters' emission technique; docs/maths.md §3.3). Only the bridge's ``G_c`` remains, and a bridge is straight, so
generalized segments through mirrors and glass need no geometry term at all. Delta lobes of mixed BSDFs count
as density 1 on both sides and void the two techniques next to them (as pbrt). Russian roulette is left out of
the densities: any weights that sum to one over the techniques keep the estimator unbiased, and these are the
same function of the path whichever technique evaluates them.

The weights are accumulated along each sub-path (Georgiev's recursive MIS, in segment form): a camera vertex
``v_j`` keeps ``U = T_{j-1}/a_j`` and ``V = [s_j bridgeable]/(G_j a_j)`` with
``T_j = Σ_{c<=j} P_c / (A_j B_{j+1})`` (its light-side density ``b_j`` is only known once the next direction
is chosen); a light vertex ``v_m`` keeps ``X = R_{m+1}/b_{m+1}`` and ``Y = [s_{m+1} bridgeable]/(G_{m+1}
b_{m+1})`` with ``R_m = Σ_{c>m} P_c G_m / (A_m B_{m+1})``. A bridge between ``v_{c-1}`` and ``v_c`` then
weighs ``1 / (1 + G_c b_c T_{c-1} + G_c a_c R_c)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..population import Surface, _select, _selection_pdf, emission_density
from ..samplers.bridge import bridge
from ..samplers.emission import emission_bounds
from ..samplers.walk import Vertex
from .sequential import _connect_sensor, adjoint_shading


def _balance(others: mi.Float) -> mi.Float:
    """Balance-heuristic weight of a technique whose density ratio sum over the other techniques is given."""
    w = dr.rcp(1.0 + others)
    return dr.select(dr.isfinite(w) & (others >= 0), w, 0.0)


def _ratio(num: mi.Float, den: mi.Float) -> mi.Float:
    return dr.select(den > 0, num / den, 0.0)


def _scalar(spectrum: mi.Spectrum) -> mi.Float:
    """A sensor's importance is grey: one channel of it."""
    return mi.unpolarized_spectrum(spectrum)[0]


#: Mitsuba's infinite and directional emitters take the scene's bounding sphere grown by this factor
#: (``1 + RayEpsilon``, 1500 x Dr.Jit's float32 epsilon 2^-24): the disc their rays start from.
_BSPHERE_GROWTH = 1.0 + 1500.0 * 2.0**-24


class EmitterTerms:
    """Per-emitter constants the technique densities of delta emitters need."""

    def __init__(self, scene: mi.Scene):
        self.scene = scene
        self.radius = float(emission_bounds(scene).bounding_sphere().radius)
        self.delta_pos_pdf = []  # (emitter, solid-angle density of its emitted directions)
        for e in scene.emitters():
            if not mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition):
                continue
            params = mi.traverse(e)
            if "cutoff_angle" in params:  # spot: directions uniform in the cutoff cone
                cos_cutoff = float(dr.cos(dr.deg2rad(mi.Float(params["cutoff_angle"])))[0])
                pdf = 1.0 / (2.0 * dr.pi * (1.0 - cos_cutoff))
            else:  # point (and other isotropic delta-position emitters)
                pdf = 1.0 / (4.0 * dr.pi)
            self.delta_pos_pdf.append((e, pdf))

    def direction_pdf(self, emitter: mi.EmitterPtr) -> mi.Float:
        pdf = dr.zeros(mi.Float, dr.width(emitter))
        for e, value in self.delta_pos_pdf:
            pdf = dr.select(emitter == mi.EmitterPtr(e), value, pdf)
        return pdf

    def delta_emission(self, emitter: mi.EmitterPtr, sel: mi.Float) -> mi.Float:
        """``E`` of a delta emitter: ``sel p_ω`` (delta position) or ``sel / (π R²)`` (delta direction)."""
        flags = emitter.flags()
        position = sel * self.direction_pdf(emitter)
        direction = sel / (dr.pi * self.radius**2)
        return dr.select(mi.has_flag(flags, mi.EmitterFlags.DeltaPosition), position, direction)

    def emission(self, ds: mi.DirectionSample3f, ref: mi.Interaction3f, sel: mi.Float, active: mi.Bool) -> mi.Float:
        """``E``: the emission technique's density of emitting from the point ``ds`` toward ``ref``, over the
        cosine there (:func:`segmitsuba.population.emission_density`, and :meth:`delta_emission`)."""
        delta = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Delta)
        e = emission_density(self.scene, ds, ref, active)
        return dr.select(active & delta, self.delta_emission(ds.emitter, sel), e)

    def emitted_weight(self, ray: mi.Ray3f, emitter: mi.EmitterPtr, sample2: mi.Point2f,
                       active: mi.Bool) -> mi.Spectrum:
        """Weight of the emitted ray ``ray``, which ``scene.sample_emitter_ray`` drew with the spatial sample
        ``sample2``, at the wavelengths the ray carries: the radiance (intensity, irradiance) emitted toward
        ``ray.d`` at ``ray.wavelengths``, over ``E``, the density of the emitted position and direction over
        the cosine there. No wavelength density: the wavelengths are the camera lane's, whose sensor weight
        holds theirs (docs/maths.md §9). In RGB this is ``sample_emitter_ray``'s own weight (tested)."""
        flags = emitter.flags()
        delta = mi.has_flag(flags, mi.EmitterFlags.Delta)
        infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite) & ~delta
        surface = active & ~delta & ~infinite
        n = dr.width(ray.o)
        # A reference point one unit along the ray: nothing below depends on where it is.
        ref = dr.zeros(mi.Interaction3f, n)
        ref.p, ref.n, ref.time, ref.wavelengths = ray.o + ray.d, -ray.d, ray.time, ray.wavelengths
        # Area lights: the emitted point again (sample_ray takes it from sample_position with sample2), for
        # its normal and texture coordinates; the ray's origin is that point spawned off the surface.
        ps, _ = emitter.sample_position(ray.time, sample2, surface)
        ds = dr.zeros(mi.DirectionSample3f, n)
        ds.p = dr.select(surface, ps.p, ray.o)
        ds.n, ds.uv, ds.time = ps.n, ps.uv, ray.time
        ds.d = -ray.d
        ds.dist = dr.select(surface, dr.norm(ref.p - ps.p), 1.0)
        ds.emitter = emitter
        ds.delta = delta
        # Point and spot lights return intensity / dist² (dist = 1), directional lights their irradiance.
        value = emitter.eval_direction(ref, ds, active & ~infinite)
        # Environments: their radiance arriving along ray.d (``eval`` looks toward -si.wi).
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi, si.time, si.wavelengths = ray.d, ray.time, ray.wavelengths
        value = dr.select(infinite, emitter.eval(si, active & infinite), value)
        sel = _selection_pdf(self.scene, emitter)
        e = self.emission(ds, ref, sel, active)
        # Environment and directional emitters emit from a disc of their own bounding-sphere radius, which
        # Mitsuba grows by (1 + RayEpsilon) over the scene's: E above uses the scene's.
        far = infinite | mi.has_flag(flags, mi.EmitterFlags.DeltaDirection)
        e = dr.select(far, e / _BSPHERE_GROWTH**2, e)
        return dr.select(active & (e > 0), value / e, 0.0)

    def nee(self, ds: mi.DirectionSample3f, ref: mi.Interaction3f, cos_ref: mi.Float,
            active: mi.Bool) -> tuple[mi.Float, mi.Float]:
        """``(E, Q)`` of the emitter point ``ds`` that emitter sampling chose from ``ref`` (cosine ``cos_ref``
        there): the emission density and ``Q = p_nee / G``, emitter sampling's density over the bridge's
        geometry term."""
        sel = _selection_pdf(self.scene, ds.emitter)
        e = self.emission(ds, ref, sel, active)
        delta_pos = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.DeltaPosition)
        q = dr.select(delta_pos, ds.pdf * dr.square(ds.dist), ds.pdf)
        return e, _ratio(q, cos_ref)


#: Sensors whose importance light tracing (technique c = 1) can sample: ``class_name()``s.
LIGHT_TRACING_SENSORS = ("PerspectiveCamera", "ThinLensCamera")


@dataclass
class LightVertices:
    """Light sub-path vertices that one bounce of the light walk reached (full width; ``valid`` masks)."""

    surf: Surface
    wi: mi.Vector3f  #: world direction back toward the previous light vertex (or the emitter)
    beta: mi.Spectrum  #: light-walk weight up to the vertex (its own BSDF excluded)
    x: mi.Float  #: recursive MIS quantities (see the module docstring)
    y: mi.Float
    depth: mi.UInt32  #: segments from the emitter to this vertex (Mitsuba's count)
    valid: mi.Bool  #: a non-delta vertex a bridge can join


class BidirectionalEstimator:
    """Consumes a light walk (stores its vertices, splats light tracing) then a camera walk (emission found,
    emitter sampling, bridges to every stored light vertex of the same lane), all MIS-weighted."""

    def __init__(self, scene: mi.Scene, sensor: mi.Sensor, sampler: mi.Sampler, max_depth: int,
                 hide_emitters: bool, n: int, light_block: mi.ImageBlock, light_scale: mi.Float):
        self.scene, self.sensor, self.sampler = scene, sensor, sampler
        self.max_depth, self.hide_emitters = max_depth, hide_emitters
        self.light_block, self.light_scale = light_block, light_scale
        self.rad = mi.BSDFContext(mi.TransportMode.Radiance)
        self.imp = mi.BSDFContext(mi.TransportMode.Importance)
        self.emitters = EmitterTerms(scene)
        # Light tracing needs the sensor's importance for any direction, sampled on the sensor as its camera rays
        # are (a pinhole or a uniformly sampled thin lens: docs/maths.md §9.2); elsewhere that technique is void
        # and the others cover its paths (as path does).
        kind = sensor.class_name()
        self.sensor_bridge = kind in LIGHT_TRACING_SENSORS
        self.lens_radius = mi.traverse(sensor)["aperture_radius"] if kind == "ThinLensCamera" else None
        self.to_sensor = sensor.world_transform().inverse()
        self.levels: list[LightVertices] = []
        self.splat_weight: mi.Spectrum | None = None
        self.radiance = dr.zeros(mi.Spectrum, n)
        self.alpha = dr.zeros(mi.Float, n)
        self._reset_last(n)

    def _reset_last(self, n: int) -> None:
        self.last_surf: Surface | None = None
        self.last_wi = dr.zeros(mi.Vector3f, n)
        self.last_p = dr.zeros(mi.Float, n)  # light: X, camera: U
        self.last_q = dr.zeros(mi.Float, n)  # light: Y, camera: V

    def _last_interaction(self, wi_world: mi.Vector3f) -> tuple[mi.SurfaceInteraction3f, mi.BSDFPtr]:
        si = self.last_surf.interaction(wi_world)
        return si, si.bsdf()

    def _remember(self, v: Vertex, mask: mi.Bool, first: float | mi.Float, second: mi.Float) -> None:
        surf = Surface.of(v.si, v.bsdf)
        self.last_surf = surf if self.last_surf is None else _select(mask, surf, self.last_surf)
        self.last_wi = dr.select(mask, -v.ray.d, self.last_wi)
        self.last_p = dr.select(mask, first, self.last_p)
        self.last_q = dr.select(mask, second, self.last_q)
        dr.schedule(self.last_surf, self.last_wi, self.last_p, self.last_q)

    # --- light sub-paths ---------------------------------------------------------------------------------

    def visit_light(self, v: Vertex) -> None:
        scene, si, seg = self.scene, v.si, v.segment
        arrive = v.active & si.is_valid() & v.ends_segment
        smooth = arrive & mi.has_flag(v.bsdf.flags(), mi.BSDFFlags.Smooth)
        d = v.ray.d
        cos_here = dr.abs(dr.dot(si.n, d))
        dist2 = dr.squared_norm(si.p - seg.origin)
        first = seg.index == 0

        # First segment, from the emitter: R of the emitter's neighbour sums emitter sampling (Q) and the
        # camera hitting the emitter (the a_k factor of both is applied when the vertex is bridged).
        fin = arrive & first
        emitter = self.light_emitter
        flags = emitter.flags()
        delta = mi.has_flag(flags, mi.EmitterFlags.Delta)
        varying = mi.has_flag(flags, mi.EmitterFlags.SpatiallyVarying) & ~mi.has_flag(flags, mi.EmitterFlags.Infinite)
        ref = dr.zeros(mi.Interaction3f, dr.width(si.p))
        ref.p, ref.n, ref.time, ref.wavelengths = si.p, si.n, si.time, si.wavelengths
        # The emitter's surface at the emitted point: seen back along a straight segment, or (through a delta
        # chain, where only a textured emitter needs it) just in front of that point.
        scale = 1e-3 * (1 + dr.max(dr.abs(seg.origin)))
        near = mi.Ray3f(seg.origin + seg.direction * scale, -seg.direction)
        near.maxt = 2 * scale
        back = dr.select(seg.straight, si.spawn_ray(-d), near)
        si_e = self.scene.ray_intersect(back, fin & ~delta & (seg.straight | varying))
        ds = mi.DirectionSample3f(scene, si=si_e, ref=ref)
        ds.p = seg.origin
        ds.d = -seg.direction
        ds.dist = dr.norm(si.p - seg.origin)
        ds.emitter = emitter
        ds.delta = delta
        sel = _selection_pdf(scene, emitter)
        e = self.emitters.emission(ds, ref, sel, fin)
        nee_pdf = scene.pdf_emitter_direction(ref, ds, fin & ~delta & seg.straight)
        delta_pos = mi.has_flag(flags, mi.EmitterFlags.DeltaPosition)
        q = dr.select(delta, dr.select(delta_pos, sel * dist2, sel), nee_pdf)
        q = _ratio(q, cos_here)
        x_first = dr.select(delta, 0.0, _ratio(1.0, e))
        y_first = dr.select(seg.straight, _ratio(q, e), 0.0)

        # Later segments: finish R of the previous light vertex now that the direction toward this one is known.
        if self.last_surf is not None:
            prev_si, prev_bsdf = self._last_interaction(seg.direction)
            cam_pdf = prev_bsdf.pdf(self.rad, prev_si, prev_si.to_local(self.last_wi), arrive & ~first)
            a_next = _ratio(cam_pdf, dr.abs(dr.dot(prev_si.n, self.last_wi)))
            r_prev = dr.select(seg.private, self.last_p, a_next * self.last_p + self.last_q)
            b = dr.select(seg.private, 1.0, _ratio(seg.pdf, dr.abs(dr.dot(seg.origin_n, seg.direction))))
            area = seg.pdf * cos_here / dr.maximum(dist2, 1e-30)  # G b: light-side area density of this vertex
            x_later = _ratio(r_prev, b)
            y_later = dr.select(seg.straight & ~seg.private, _ratio(1.0, area), 0.0)
        else:
            x_later, y_later = mi.Float(0), mi.Float(0)
        x = dr.select(first, x_first, x_later)
        y = dr.select(first, y_first, y_later)

        self.levels.append(LightVertices(surf=Surface.of(si, v.bsdf), wi=-d, beta=mi.Spectrum(v.throughput), x=x,
                                         y=y, depth=mi.UInt32(v.depth), valid=mi.Bool(smooth)))
        dr.schedule(self.levels[-1])
        self._remember(v, arrive, x, y)

        if self.sensor_bridge:
            self._light_tracing(v, smooth, x, y)

    def _light_tracing(self, v: Vertex, active: mi.Bool, x: mi.Float, y: mi.Float) -> None:
        """Technique c = 1: bridge from a light vertex to the sensor, splatted."""
        si = v.si
        sensor_ds, importance = self.sensor.sample_direction(si, self.sampler.next_2d(active), active)
        local = si.to_local(sensor_ds.d)
        wi_dot_n = dr.dot(si.n, si.to_world(si.wi))
        wo_dot_n = dr.dot(si.n, sensor_ds.d)
        surface = adjoint_shading(si, sensor_ds.d) * v.bsdf.eval(self.imp, si, local, active)
        # G_1 a_1: the sensor's area density at this vertex (its solid-angle density is importance * dist²)
        camera_area = _scalar(importance) * dr.abs(wo_dot_n)
        si_cam = mi.SurfaceInteraction3f(si)
        si_cam.wi = local
        cam_pdf = v.bsdf.pdf(self.rad, si_cam, si.wi, active)
        a_next = _ratio(cam_pdf, dr.abs(wi_dot_n))
        w = _balance(camera_area * (a_next * x + y))
        weight = v.throughput * importance * self.light_scale * w
        if self.splat_weight is not None:
            weight *= self.splat_weight
        # (a copy of the mask: _connect_sensor narrows it in place)
        _connect_sensor(self.scene, self.sensor, self.light_block, si, sensor_ds, weight, surface, 0.0,
                        mi.Bool(active))

    def start_light(self, emitter: mi.EmitterPtr, splat_weight: mi.Spectrum | None = None) -> None:
        """The light sub-paths about to be visited were emitted by ``emitter``; their light-tracing splats are
        multiplied by ``splat_weight`` if given (spectral: the camera lanes' wavelength weight)."""
        self.light_emitter = emitter
        self.splat_weight = splat_weight

    def start_camera(self, n: int) -> None:
        self._reset_last(n)

    # --- camera sub-paths --------------------------------------------------------------------------------

    def visit_camera(self, v: Vertex) -> None:
        scene, si, seg = self.scene, v.si, v.segment
        arrive = v.active & v.ends_segment
        valid = si.is_valid()
        d = v.ray.d
        cos_here = dr.abs(dr.dot(si.n, d))
        dist2 = dr.squared_norm(si.p - seg.origin)
        first = seg.index == 0
        delta = seg.private  # the segment left its origin through a delta lobe

        # U, V of this vertex (T_{j-1} needs the light-side density at the previous vertex, known now).
        if self.last_surf is not None:
            prev_si, prev_bsdf = self._last_interaction(seg.direction)
            light_pdf = prev_bsdf.pdf(self.imp, prev_si, prev_si.to_local(self.last_wi), arrive & ~first)
            b_prev = _ratio(light_pdf, dr.abs(dr.dot(prev_si.n, self.last_wi)))
            t_prev = dr.select(delta, self.last_p, self.last_p * b_prev + self.last_q)
        else:
            t_prev = mi.Float(0)
        a = dr.select(delta, 1.0, _ratio(seg.pdf, dr.abs(dr.dot(seg.origin_n, seg.direction))))
        area = seg.pdf * cos_here / dr.maximum(dist2, 1e-30)  # G a: camera-side area density here
        if self.sensor_bridge:
            # G_1 a_1: the sensor's area density of this vertex given the lens point the camera ray left from
            # (the light-tracing technique samples that point with the camera's own density, which cancels).
            _, importance = self.sensor.sample_direction(si, self._lens_sample(seg), arrive & first & valid)
            area_first = _scalar(importance) * cos_here
        else:
            area_first = mi.Float(0)
        u = dr.select(first, 0.0, _ratio(t_prev, a))
        bridgeable = seg.straight & ~delta & (~first | self.sensor_bridge)
        v_mis = dr.select(bridgeable, _ratio(1.0, dr.select(first, area_first, area)), 0.0)

        # Technique k+1: the walk found an emitter (or escaped into an environment).
        ds = mi.DirectionSample3f(scene, si=si, ref=v.prev)
        seen = arrive & ~(first & (v.depth == 0) & self.hide_emitters)
        le = ds.emitter.eval(si, seen)
        emitting = seen & dr.any(mi.unpolarized_spectrum(le) != 0)
        nee_pdf = scene.pdf_emitter_direction(v.prev, ds, emitting & ~first & seg.straight & ~delta)
        q = _ratio(nee_pdf, dr.abs(dr.dot(seg.origin_n, seg.direction)))
        e = self.emitters.emission(ds, v.prev, _selection_pdf(scene, ds.emitter), emitting & ~first)
        others = _ratio(dr.select(seg.straight & ~delta, q, 0.0), a) + e * u
        w = dr.select(first, 1.0, _balance(others))
        radiance = self.radiance + dr.select(emitting, v.throughput * w * le, 0)

        # The rest needs a surface vertex with a non-delta lobe, where a path of one more segment is allowed.
        at = arrive & valid & mi.has_flag(v.bsdf.flags(), mi.BSDFFlags.Smooth)
        wi_world = -d

        # Technique k: emitter sampling (a bridge to a point sampled on an emitter).
        active_em = at & v.continues
        ds, em_weight = scene.sample_emitter_direction(si, self.sampler.next_2d(active_em), True, active_em)
        active_em &= ds.pdf != 0
        wo = si.to_local(ds.d)
        value, bsdf_pdf = v.bsdf.eval_pdf(self.rad, si, wo, active_em)
        cos_em = dr.abs(dr.dot(si.n, ds.d))
        e, q = self.emitters.nee(ds, si, cos_em, active_em)
        si_rev = mi.SurfaceInteraction3f(si)
        si_rev.wi = wo
        light_pdf = v.bsdf.pdf(self.imp, si_rev, si.wi, active_em)
        t_here = u * _ratio(light_pdf, dr.abs(dr.dot(si.n, wi_world))) + v_mis
        hit = dr.select(ds.delta, 0.0, _ratio(bsdf_pdf, cos_em))
        w = _balance(_ratio(hit + e * t_here, q))
        radiance += dr.select(active_em, v.throughput * value * em_weight * w, 0)

        first_hit = v.active & (v.depth == 0) & valid & ~mi.has_flag(v.bsdf.flags(), mi.BSDFFlags.Null)
        self.alpha = dr.select(first_hit, 1.0, self.alpha)
        self._remember(v, arrive & valid, u, v_mis)

        # Techniques 2 .. k-1: bridges to the light vertices of the same lane, one small kernel each (the same
        # code for every level and depth, so it compiles once), from the camera vertex in compact form (not
        # re-traced by every bridge).
        camera = Surface.of(si, v.bsdf)
        wi_world = mi.Vector3f(wi_world)
        dr.eval(radiance, self.alpha, camera, wi_world, at, u, v_mis, v.throughput, v.depth)
        for level in self.levels:
            active = at & level.valid & (v.depth + level.depth + 2 <= self.max_depth)
            if not dr.any(active):  # a cheap reduction over a mask already computed: skip empty levels
                continue
            radiance += self._bridge(camera, wi_world, v.throughput, level, u, v_mis, active)
            dr.eval(radiance)
        self.radiance = radiance
        dr.eval()

    def _lens_sample(self, seg) -> mi.Point2f:
        """The ``sensor.sample_direction`` sample that picks the lens point the camera ray ``seg`` left from."""
        if self.lens_radius is None:
            return mi.Point2f(0.5)  # a pinhole: every sample is the same point
        o = self.to_sensor @ mi.Point3f(seg.origin)  # the ray starts at the near clip plane: back to z = 0
        d = self.to_sensor @ mi.Vector3f(seg.direction)
        lens = o - d * (o.z / d.z)
        u = mi.warp.uniform_disk_to_square_concentric(mi.Point2f(lens.x, lens.y) / self.lens_radius)
        return dr.clip(u, 0.0, 1.0)

    def _bridge(self, camera: Surface, wi_world: mi.Vector3f, throughput: mi.Spectrum, level: LightVertices,
                u: mi.Float, v_mis: mi.Float, active: mi.Bool) -> mi.Spectrum:
        si = camera.interaction(wi_world)
        bsdf = si.bsdf()
        b = bridge(self.scene, si, level.surf.p, level.surf.n, active)
        active = b.visible
        # camera end: radiance-mode BSDF toward the light vertex, and the light sampler's reverse density
        wo = si.to_local(b.d)
        f_cam, pdf_cam = bsdf.eval_pdf(self.rad, si, wo, active)
        si_rev = mi.SurfaceInteraction3f(si)
        si_rev.wi = wo
        pdf_cam_rev = bsdf.pdf(self.imp, si_rev, si.wi, active)
        # light end: adjoint BSDF toward the camera vertex (shading-normal correction as light tracing)
        sl = level.surf.interaction(level.wi)
        bsdf_l = sl.bsdf()
        wo_l = sl.to_local(-b.d)
        f_light, pdf_light = bsdf_l.eval_pdf(self.imp, sl, wo_l, active)
        f_light *= adjoint_shading(sl, -b.d)
        sl_rev = mi.SurfaceInteraction3f(sl)
        sl_rev.wi = wo_l
        pdf_light_rev = bsdf_l.pdf(self.rad, sl_rev, sl.wi, active)

        inv_d2 = dr.rcp(b.dist2)
        t = u * _ratio(pdf_cam_rev, dr.abs(dr.dot(si.n, wi_world))) + v_mis
        r = _ratio(pdf_light_rev, dr.abs(dr.dot(sl.n, level.wi))) * level.x + level.y
        others = pdf_light * b.cos_camera * inv_d2 * t + pdf_cam * b.cos_light * inv_d2 * r
        w = _balance(others)
        value = throughput * f_cam * f_light * level.beta * (inv_d2 * w)
        return dr.select(active, value, 0)
