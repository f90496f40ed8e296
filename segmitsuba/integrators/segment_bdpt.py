"""``segment_bdpt``: camera and light segment samplers + the bridge segment sampler, combined with MIS."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..estimators.bdpt import BidirectionalEstimator
from ..film import film_sample_count, prepare_sampler, splat_camera_samples, splat_coverage
from ..samplers.camera import CameraSegmentSampler
from ..samplers.light import LightSegmentSampler
from .base import SegmentIntegrator, check_scene


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

    Light tracing needs a pinhole ``perspective`` sensor; with other sensors that technique is left out and
    the others cover its paths, as in ``path``. Spectral variants are refused: a bridge joins two sub-paths
    that must carry the same wavelengths, while Mitsuba samples the emitters' and the sensor's wavelengths
    separately.

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

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        if mi.is_spectral:
            raise RuntimeError(
                "segment_bdpt: spectral variants are not supported (a bridge joins a camera and a light "
                "sub-path, which Mitsuba samples with different wavelengths). Use an RGB or mono variant, "
                "or segment_pt / segment_lt."
            )
        self.camera_sampler = CameraSegmentSampler(self.depth_limit, self.rr_depth)
        self.light_sampler = LightSegmentSampler(self.depth_limit, self.rr_depth)

    def _coverage(self, film: mi.Film, block: mi.ImageBlock) -> mi.TensorXf:
        key = (tuple(film.crop_size()), tuple(film.crop_offset()), str(film.rfilter()))
        if getattr(self, "_coverage_key", None) != key:
            self._coverage_key, self._coverage_value = key, splat_coverage(film, block)
        return self._coverage_value

    def render(self, scene: mi.Scene, sensor: int | mi.Sensor = 0, seed: int = 0, spp: int = 0,
               develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        check_scene(self.plugin_name, scene, sensor, light_paths=True)
        film = sensor.film()
        spp = spp or sensor.sampler().sample_count()
        n = film_sample_count(film) * spp
        film.prepare([])
        camera_block = film.create_block()
        camera_block.set_offset(film.crop_offset())
        camera_block.set_coalesce(camera_block.coalesce() and spp >= 4)
        # Light tracing splats (technique c = 1) go to their own block: they are not normalized by the
        # filter weights of the camera samples, so the two images are developed apart and summed, the splats
        # divided by the filter coverage of each pixel (film.splat_coverage), as camera samples are.
        light_block = film.create_block(mi.ScalarVector2u(0), True, False)
        light_block.set_offset(film.crop_offset())
        light_block.set_coalesce(False)
        light_scale = dr.opaque(mi.Float, float(dr.prod(film.crop_size())) / n)  # opaque: no recompiles per spp
        with dr.suspend_grad():
            sampler = prepare_sampler(sensor, seed, spp, n)
            estimator = BidirectionalEstimator(scene, sensor, sampler, self.depth_limit, self.hide_emitters, n,
                                               light_block, light_scale)
            if len(scene.emitters()) > 0 and (self.max_depth == -1 or self.max_depth > 1):
                lights = self.light_sampler.sample(scene, sensor, sampler, n)
                estimator.start_light(lights.emitter)
                for vertex in lights.walk:
                    estimator.visit_light(vertex)
            estimator.start_camera(n)
            paths = self.camera_sampler.sample(scene, sensor, sampler, spp, self.hide_emitters)
            for vertex in paths.walk:
                estimator.visit_camera(vertex)
            splat_camera_samples(film, camera_block, paths.position, paths.sensor_weight * estimator.radiance,
                                 paths.wavelengths, estimator.alpha)
            if not develop:
                raise RuntimeError("segment_bdpt: develop=False is not supported (its light-tracing image is "
                                   "developed separately from the camera samples)")
            film.put_block(light_block)
            light_image = film.develop() / self._coverage(film, light_block)
            dr.eval(light_image)
            film.prepare([])
            film.put_block(camera_block)
            image = film.develop() + light_image
            if evaluate:
                dr.eval(image)
            return image


mi.register_integrator("segment_bdpt", lambda props: SegmentBDPT(props))
