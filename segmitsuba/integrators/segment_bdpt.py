"""``segment_bdpt``: camera and light segment samplers + the bridge segment sampler, combined with MIS."""

from __future__ import annotations

import mitsuba as mi

from ..estimators.bdpt import BidirectionalEstimator
from ..film import FilmTarget, film_sample_count, prepare_sampler
from ..samplers.camera import CameraSegmentSampler
from ..samplers.light import LightSegmentSampler
from .base import SegmentIntegrator


class SegmentBDPT(SegmentIntegrator):
    r"""
    Segment bidirectional path tracer (:monosp:`segment_bdpt`)
    ----------------------------------------------------------

    Every sample traces one camera and one light sub-path of (generalized) segments and joins them in every
    possible way: the camera sub-path finding an emitter, emitter sampling, a bridge segment from each camera
    vertex to each light vertex, and light tracing (a bridge to the sensor, splatted). The techniques are
    combined with the balance heuristic (``segmitsuba/estimators/bdpt.py``). Unbiased: it converges to
    ``path``'s image, and also reaches the paths only light tracing finds (a delta emitter seen through a
    mirror or glass on a diffuse surface).

    Sensors: light tracing works with ``perspective`` and ``thinlens`` sensors (the MIS weights use the
    density of the lens point each camera ray left from). With other sensors (``orthographic``: a delta
    direction) that technique is left out and the others cover its paths, as in ``path``.

    Variants: RGB, mono and spectral. In spectral variants the light sub-path of each sample carries the
    wavelengths of its camera sample, so that bridges join sub-paths of one set of wavelengths: the emitted
    radiance is evaluated at them and divided by the position and direction densities only, since their
    density is already in the camera sample's weight; light-tracing splats take that weight too
    (``docs/maths.md`` §9).

    ``develop=False`` follows Mitsuba: nothing is returned, and the sensor's film holds the camera samples and
    the light-tracing splats together, so that a later ``film.develop()`` gives the image ``develop=True``
    returns.

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path, in segments between sensor and emitter (Mitsuba's definition, delta bounces
         included); -1 is unbounded. (Default: -1, as ``path``)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts, on both sub-paths; applied at segment vertices only.
         (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)
    """

    plugin_name = "segment_bdpt"
    default_max_depth = -1  # as Mitsuba's path
    uses_light_paths = True
    normalize_light = True

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.camera_sampler = CameraSegmentSampler(self.depth_limit, self.rr_depth)
        self.light_sampler = LightSegmentSampler(self.depth_limit, self.rr_depth)

    def render_samples(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, seed: int, spp: int) -> None:
        n = film_sample_count(target.film) * spp
        # Light tracing splats (technique c = 1) go to the target's light block: they are not normalized by the
        # filter weights of the camera samples, so the two images are developed apart and summed, the splats
        # divided by the filter coverage of each pixel (normalize_light), as camera samples are.
        sampler = prepare_sampler(sensor, seed, spp, n)
        estimator = BidirectionalEstimator(scene, sensor, sampler, self.depth_limit, self.hide_emitters, n,
                                           target.light_block, target.light_scale(n))
        # Spectral variants: the camera rays first (their walk is traced below), since their wavelengths are the
        # whole lane's and the light sub-path carries them too (docs/maths.md §9). RGB and mono keep the light
        # sub-paths first, and with them the random numbers of earlier versions.
        paths = self.camera_sampler.sample(scene, sensor, sampler, spp, self.hide_emitters) if mi.is_spectral else None
        if len(scene.emitters()) > 0 and (self.max_depth == -1 or self.max_depth > 1):
            if mi.is_spectral:
                lights = self.light_sampler.sample(scene, sensor, sampler, n, wavelengths=paths.wavelengths,
                                                   emitted=estimator.emitters.emitted_weight)
                # A light-tracing splat is a sample of the camera lane's wavelengths: it takes their sensor
                # weight (its spatial part is 1 for the sensors light tracing supports).
                estimator.start_light(lights.emitter, paths.sensor_weight)
            else:
                lights = self.light_sampler.sample(scene, sensor, sampler, n)
                estimator.start_light(lights.emitter)
            for vertex in lights.walk:
                estimator.visit_light(vertex)
        if paths is None:
            paths = self.camera_sampler.sample(scene, sensor, sampler, spp, self.hide_emitters)
        estimator.start_camera(n)
        for vertex in paths.walk:
            estimator.visit_camera(vertex)
        target.splat_camera(paths.position, paths.sensor_weight * estimator.radiance, paths.wavelengths,
                            estimator.alpha)


mi.register_integrator("segment_bdpt", lambda props: SegmentBDPT(props))
