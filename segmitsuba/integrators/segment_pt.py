"""``segment_pt``: camera segment sampler × sequential estimation (segment path tracing)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..estimators.sequential import PathEstimator
from ..film import develop_film, film_sample_count, prepare_sampler, splat_camera_samples
from ..samplers.camera import CameraSegmentSampler
from .base import SegmentIntegrator, check_scene


class SegmentPathTracer(SegmentIntegrator):
    r"""
    Segment path tracer (:monosp:`segment_pt`)
    ------------------------------------------

    Camera segment sampler combined with sequential estimation: one segment path per sample, with emitter
    sampling and power-heuristic MIS as Mitsuba's ``path``. Unbiased; it converges to ``path``'s image.

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path, in segments between sensor and emitter (Mitsuba's definition, delta bounces
         included); -1 is unbounded. (Default: -1, as ``path``)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts; applied at segment vertices only. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)
    """

    plugin_name = "segment_pt"
    default_max_depth = -1  # as Mitsuba's path

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.sampler_kind = CameraSegmentSampler(self.depth_limit, self.rr_depth)

    def render(self, scene: mi.Scene, sensor: int | mi.Sensor = 0, seed: int = 0, spp: int = 0,
               develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        check_scene(self.plugin_name, scene, sensor)
        film = sensor.film()
        spp = spp or sensor.sampler().sample_count()
        film.prepare([])
        block = film.create_block()
        block.set_offset(film.crop_offset())  # pixel positions are absolute (Mitsuba's prb forgets this)
        block.set_coalesce(block.coalesce() and spp >= 4)
        with dr.suspend_grad():
            sampler = prepare_sampler(sensor, seed, spp, film_sample_count(film) * spp)
            paths = self.sampler_kind.sample(scene, sensor, sampler, spp, self.hide_emitters)
            estimator = PathEstimator(scene, sampler, self.depth_limit, self.hide_emitters, dr.width(paths.position))
            for vertex in paths.walk:
                estimator.visit(vertex)
            splat_camera_samples(film, block, paths.position, paths.sensor_weight * estimator.radiance,
                                 paths.wavelengths, estimator.alpha)
            return develop_film(film, block, develop, evaluate)


mi.register_integrator("segment_pt", lambda props: SegmentPathTracer(props))
