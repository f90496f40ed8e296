"""Sequential estimation: one segment path per sample, ``g / p`` (talk: "practical algorithms").

* ``PathEstimator`` consumes a camera walk: emission found by the walk and emitter sampling at every segment
  vertex, combined with the power heuristic exactly as Mitsuba's ``path`` (so their noise is comparable).
* ``LightTracingEstimator`` consumes a light walk: every vertex is connected to the sensor and splatted, as
  Mitsuba's ``ptracer``; ``splat_visible_emitters`` adds the emitters the sensor sees directly.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..samplers.emission import sample_wavelengths
from ..samplers.walk import Vertex


def power_heuristic(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


class PathEstimator:
    """Radiance of camera sub-paths, accumulated vertex by vertex."""

    def __init__(self, scene: mi.Scene, sampler: mi.Sampler, max_depth: int, hide_emitters: bool, n: int):
        self.scene = scene
        self.sampler = sampler
        self.max_depth = max_depth
        self.hide_emitters = hide_emitters
        self.ctx = mi.BSDFContext(mi.TransportMode.Radiance)
        self.radiance = dr.zeros(mi.Spectrum, n)
        self.alpha = dr.zeros(mi.Float, n)

    def visit(self, v: Vertex) -> None:
        scene, si = self.scene, v.si
        valid = si.is_valid()

        # Emission reached by the walk, weighted against emitter sampling at the previous vertex.
        ds = mi.DirectionSample3f(scene, si=si, ref=v.prev)
        em_pdf = scene.pdf_emitter_direction(v.prev, ds, v.active & ~v.prev_delta)
        mis = dr.select(v.prev_delta, 1.0, power_heuristic(v.prev_pdf, em_pdf))
        seen = v.active
        if self.hide_emitters:
            seen &= v.depth > 0
        le = ds.emitter.eval(si, seen)
        radiance = self.radiance + dr.select(seen, v.throughput * mis * le, 0)

        # Emitter sampling (next-event estimation) where a path of one more segment is allowed.
        active_em = v.continues & mi.has_flag(v.bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_weight = scene.sample_emitter_direction(si, self.sampler.next_2d(v.continues), True, active_em)
        active_em &= ds.pdf != 0
        value, bsdf_pdf = v.bsdf.eval_pdf(self.ctx, si, si.to_local(ds.d), active_em)
        mis_em = dr.select(ds.delta, 1.0, power_heuristic(ds.pdf, bsdf_pdf))
        radiance += dr.select(active_em, v.throughput * mis_em * value * em_weight, 0)

        self.radiance = radiance
        first_hit = v.active & (v.depth == 0) & valid & ~mi.has_flag(v.bsdf.flags(), mi.BSDFFlags.Null)
        self.alpha = dr.select(first_hit, 1.0, self.alpha)
        dr.schedule(self.radiance, self.alpha)


def adjoint_shading(si: mi.SurfaceInteraction3f, wo: mi.Vector3f) -> mi.Float:
    """Factor that turns ``bsdf.eval`` in importance mode into the adjoint BSDF with shading normals [Veach
    1997, p. 155] for the world direction ``wo``; 0 where the geometric and shading normals disagree about a
    side (no light leaks), as ``ptracer``."""
    local = si.to_local(wo)
    wi_dot_n = dr.dot(si.n, si.to_world(si.wi))
    wo_dot_n = dr.dot(si.n, wo)
    ok = (wi_dot_n * mi.Frame3f.cos_theta(si.wi) > 0) & (wo_dot_n * mi.Frame3f.cos_theta(local) > 0)
    return dr.select(ok, dr.abs((mi.Frame3f.cos_theta(si.wi) * wo_dot_n) / (mi.Frame3f.cos_theta(local) * wi_dot_n)),
                     0)


#: sensors whose importance light tracing splats consistently: image planes (a batch of them too)
CONNECTABLE_SENSORS = ("PerspectiveCamera", "ThinLensCamera", "BatchSensor")


def sensor_connects(sensor: mi.Sensor) -> bool:
    """Whether light tracing can connect to ``sensor``: it samples a direction toward a point (perspective, thin
    lens; not orthographic and other sensors with a delta direction, where Mitsuba raises
    ``Endpoint::sample_direction(): not implemented``) and forms an image (:data:`CONNECTABLE_SENSORS`:
    ``irradiancemeter`` samples directions too, but Mitsuba's ``ptracer`` renders 22x ``path``'s value through
    it)."""
    if sensor.class_name() not in CONNECTABLE_SENSORS:
        return False
    it = dr.zeros(mi.Interaction3f, 1)
    it.p = sensor.world_transform() @ mi.Point3f(0, 0, 1)
    try:
        dr.eval(sensor.sample_direction(it, mi.Point2f(0.5), True))
    except RuntimeError:
        return False
    return True


def _connect_sensor(scene: mi.Scene, sensor: mi.Sensor, block: mi.ImageBlock, si: mi.SurfaceInteraction3f,
                    sensor_ds: mi.DirectionSample3f, weight: mi.Spectrum, surface_weight: mi.Spectrum,
                    alpha: float, active: mi.Bool) -> None:
    """Shadow-test the connection to the sensor and splat (ptracer's ``connect_sensor``)."""
    active &= (sensor_ds.pdf > 0) & dr.any(mi.unpolarized_spectrum(weight) != 0)
    ray = si.spawn_ray_to(sensor_ds.p)
    active &= ~scene.ray_test(ray, active)
    pos = sensor_ds.uv + mi.Vector2f(block.offset())
    value = mi.unpolarized_spectrum(weight * surface_weight) if mi.is_polarized else weight * surface_weight
    block.put(pos, si.wavelengths, value, alpha, 0.0, active)


class LightTracingEstimator:
    """Splats every light-walk vertex's contribution through the sensor (importance transport)."""

    def __init__(self, scene: mi.Scene, sensor: mi.Sensor, sampler: mi.Sampler, block: mi.ImageBlock,
                 scale: float):
        self.scene, self.sensor, self.sampler, self.block, self.scale = scene, sensor, sampler, block, scale
        self.ctx = mi.BSDFContext(mi.TransportMode.Importance)

    def visit(self, v: Vertex) -> None:
        si = v.si
        active = v.active & si.is_valid()
        sensor_ds, sensor_weight = self.sensor.sample_direction(si, self.sampler.next_2d(active), active)
        surface = adjoint_shading(si, sensor_ds.d) * v.bsdf.eval(self.ctx, si, si.to_local(sensor_ds.d), active)
        _connect_sensor(self.scene, self.sensor, self.block, si, sensor_ds, v.throughput * sensor_weight * self.scale,
                        surface, 1.0, active)


def splat_visible_emitters(scene: mi.Scene, sensor: mi.Sensor, sampler: mi.Sampler, block: mi.ImageBlock,
                           scale: float, n: int) -> None:
    """Emitters seen directly by the sensor, connected from a sampled emitter point (as ``ptracer``)."""
    time = dr.full(mi.Float, sensor.shutter_open(), n)
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    index, index_weight, _ = scene.sample_emitter(sampler.next_1d())
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index)
    flags = emitter.flags()
    active = ~mi.has_flag(flags, mi.EmitterFlags.Delta)
    infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    emitter_weight = dr.zeros(mi.Spectrum, n)
    # Infinite emitters: a direction from the sensor's position, converted to area measure.
    ref = dr.zeros(mi.Interaction3f, n)
    ref.time = time
    ref.p = mi.Point3f(sensor.world_transform().translation())
    active_inf = active & infinite
    s = sampler.next_2d()
    ds, _ = emitter.sample_direction(ref, s, active_inf)
    emitter_weight[active_inf] = dr.select(ds.pdf > 0, dr.rcp(ds.pdf), 0) * dr.square(ds.dist)
    si[active_inf] = mi.SurfaceInteraction3f(ds, ref.wavelengths)
    # Finite emitters: a position on the emitter.
    active_fin = active & ~infinite
    ps, pos_weight = emitter.sample_position(time, sampler.next_2d(), active_fin)
    emitter_weight[active_fin] = pos_weight
    si[active_fin] = mi.SurfaceInteraction3f(ps, ref.wavelengths)

    sensor_ds, sensor_weight = sensor.sample_direction(si, sampler.next_2d(), active)
    si.wi = sensor_ds.d
    wavelengths, wav_weight = sample_wavelengths(scene, index, si, sampler.next_1d(active), active)
    si.wavelengths = wavelengths
    si.shape = emitter.get_shape()
    weight = index_weight * emitter_weight * wav_weight * sensor_weight * scale
    # Foreshortening at the emitter surface (none for infinite emitters), and never from behind.
    local = si.to_local(sensor_ds.d)
    on_surface = active & (si.shape != None)  # noqa: E711 (Dr.Jit pointer test)
    surface = dr.select(on_surface, dr.maximum(0, mi.Frame3f.cos_theta(local)), 1.0)
    surface = dr.select(~on_surface & (mi.Frame3f.cos_theta(local) <= 0), 0, surface)
    _connect_sensor(scene, sensor, block, si, sensor_ds, weight, mi.Spectrum(surface), 0.0, active)
