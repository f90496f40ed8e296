"""``segment_pt``: camera segment sampler × sequential estimation (segment path tracing)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..estimators.sequential import PathEstimator
from ..film import FilmTarget, film_sample_count, prepare_sampler
from ..samplers.camera import CameraSegmentSampler
from .base import SegmentIntegrator


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
    needs_consistent_emitters = False  # emitter sampling and MIS as path's: it renders what path renders

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.sampler_kind = CameraSegmentSampler(self.depth_limit, self.rr_depth)

    def render_samples(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, seed: int, spp: int) -> None:
        sampler = prepare_sampler(sensor, seed, spp, film_sample_count(target.film) * spp)
        paths = self.sampler_kind.sample(scene, sensor, sampler, spp, self.hide_emitters)
        estimator = PathEstimator(scene, sampler, self.depth_limit, self.hide_emitters, dr.width(paths.position))
        for vertex in paths.walk:
            estimator.visit(vertex)
        target.splat_camera(paths.position, paths.sensor_weight * estimator.radiance, paths.wavelengths,
                            estimator.alpha)


mi.register_integrator("segment_pt", lambda props: SegmentPathTracer(props))
