"""``segment_lt``: light segment sampler × sequential estimation (segment light tracing)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..estimators.sequential import LightTracingEstimator, sensor_connects, splat_visible_emitters
from ..film import FilmTarget, prepare_sampler
from ..samplers.light import LightSegmentSampler
from .base import SegmentIntegrator


def check_sensor(plugin: str, sensor: mi.Sensor) -> None:
    """Light tracing connects every vertex to the sensor: refuse sensors it cannot connect to
    (:func:`~segmitsuba.estimators.sequential.sensor_connects`), naming them. Mitsuba's ``ptracer`` fails on
    most with ``Endpoint::sample_direction(): not implemented``."""
    if not sensor_connects(sensor):
        raise RuntimeError(
            f"{plugin}: light tracing needs a sensor whose image it can splat to (perspective, thinlens, or a batch "
            f"of them), not a {sensor.class_name()}. Use segment_pt or segment_bdpt, which render it without "
            "the light-tracing technique."
        )


class SegmentLightTracer(SegmentIntegrator):
    r"""
    Segment light tracer (:monosp:`segment_lt`)
    -------------------------------------------

    Light segment sampler combined with sequential estimation: every vertex of a light sub-path is connected
    to the sensor and splatted, as Mitsuba's ``ptracer``. Unbiased; it converges to ``ptracer``'s image and
    reaches paths ``path`` cannot (delta emitter → specular → diffuse).

    Sensors: ``perspective`` and ``thinlens`` (and a ``batch`` of them); ``orthographic``, the meters and
    ``distant`` are refused with a clear error (:func:`~segmitsuba.estimators.sequential.sensor_connects`). RGB,
    mono and spectral variants (each light sub-path carries the wavelengths its emitter sampled, as in
    ``ptracer``).

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path, in segments between emitter and sensor (Mitsuba's definition); -1 is unbounded.
         (Default: -1, as ``ptracer``)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts; applied at segment vertices only. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)
    """

    plugin_name = "segment_lt"
    default_max_depth = -1  # as Mitsuba's ptracer
    uses_light_paths = True

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.sampler_kind = LightSegmentSampler(self.depth_limit, self.rr_depth)

    def render_samples(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, seed: int, spp: int) -> None:
        check_sensor(self.plugin_name, sensor)
        # As ptracer: spp light paths per film pixel, splatted into a normalized block.
        count = int(dr.prod(target.film.size())) * spp
        block, scale = target.light_block, target.light_scale(count)
        if len(scene.emitters()) == 0 or self.max_depth == 0:
            return
        sampler = prepare_sampler(sensor, seed, spp, count)
        if not self.hide_emitters:
            splat_visible_emitters(scene, sensor, sampler, block, scale, count)
        paths = self.sampler_kind.sample(scene, sensor, sampler, count)
        estimator = LightTracingEstimator(scene, sensor, sampler, block, scale)
        for vertex in paths.walk:
            estimator.visit(vertex)


mi.register_integrator("segment_lt", lambda props: SegmentLightTracer(props))
