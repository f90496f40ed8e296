"""Camera segment sampler: first segments from the sensor (``p_W ∝ W G``), then BSDF-sampled children."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import drjit as dr
import mitsuba as mi

from ..film import film_sample_size
from .walk import RandomWalk, Vertex


def sample_sensor_ray(sensor: mi.Sensor, time: mi.Float, wavelength_sample: mi.Float, position_sample: mi.Point2f,
                      aperture_sample: mi.Point2f) -> tuple[mi.Ray3f, mi.Spectrum]:
    """``sensor.sample_ray``, through ``sample_ray_differential`` as Mitsuba's own integrators call it: some
    sensors implement only that one (``irradiancemeter``). The differentials are dropped, never computed."""
    ray, weight = sensor.sample_ray_differential(time, wavelength_sample, position_sample, aperture_sample)
    return mi.Ray3f(ray), weight


def sample_camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, spp: int, wavelength_sample: float | None = None,
                       pixels: mi.UInt32 | None = None):
    """One ray per (pixel, sample), as Mitsuba's own integrators generate them; ``pixels``: only these film
    samples (indices in raster order of the sampled film, border included), ``spp`` each.

    ``wavelength_sample`` (spectral variants): one uniform number that every ray takes as its wavelength sample
    instead of its own, so that all of them carry the same wavelengths (the filters' pools, docs/maths.md §10).
    The sampler still draws its own, so the other random numbers do not move.

    Returns ``(ray, weight, splat position)``; the position is continuous unless the filter is a box.
    """
    film = sensor.film()
    film_size = film_sample_size(film)
    rfilter = film.rfilter()
    border = rfilter.border_size()
    count = int(dr.prod(film_size)) if pixels is None else dr.width(pixels)
    idx = dr.arange(mi.UInt32, count * spp) // dr.opaque(mi.UInt32, spp)
    if pixels is not None:
        idx = dr.gather(mi.UInt32, pixels, idx)
    pos = mi.Vector2i()
    pos.y = mi.Int32(idx // film_size[0])
    pos.x = mi.Int32(idx - mi.UInt32(pos.y) * film_size[0])
    if film.sample_border():
        pos -= border
    pos += mi.Vector2i(film.crop_offset())
    pos_f = mi.Vector2f(pos) + sampler.next_2d()
    scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
    offset = -mi.ScalarVector2f(film.crop_offset()) * scale
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Vector2f(0.5)
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    wav = sampler.next_1d() if mi.is_spectral else mi.Float(0.5)
    if wavelength_sample is not None and mi.is_spectral:
        # opaque: a literal would be compiled into the kernels, anew for every value
        wav = dr.opaque(mi.Float, wavelength_sample, dr.width(pos_f))
    ray, weight = sample_sensor_ray(sensor, time, wav, dr.fma(pos_f, scale, offset), aperture)
    splat_pos = mi.Vector2f(pos) if rfilter.is_box_filter() else pos_f
    return ray, weight, splat_pos


@dataclass
class CameraSubpaths:
    """A wavefront of camera sub-paths: where each lands on the film and the walk that extends it."""

    position: mi.Vector2f  #: splat position on the film
    sensor_weight: mi.Spectrum  #: sensor importance / pdf of the primary ray
    wavelengths: object
    walk: Iterator[Vertex]  #: the walk, vertex by vertex (wavefront)
    #: the same walk as symbolic loops with a consumer in their body (``record(recorder)``, see
    #: :meth:`RandomWalk.record`); a sub-path wavefront is walked one way or the other, once
    record: Callable[[Any], None]


class CameraSegmentSampler:
    def __init__(self, max_depth: int, rr_depth: int, max_segments: int = 0xFFFFFFFF, for_pool: bool = False,
                 follow_delta_lobes: bool = False, drop_delta_lobes: bool = False, private_glossy: bool = False):
        self.walker = RandomWalk(mi.TransportMode.Radiance, max_depth, rr_depth, max_segments,
                                 keep_zero_weight=for_pool, follow_delta_lobes=follow_delta_lobes,
                                 drop_delta_lobes=drop_delta_lobes, private_glossy=private_glossy)

    def sample(self, scene: mi.Scene, sensor: mi.Sensor, sampler: mi.Sampler, spp: int,
               hide_emitters: bool = False, wavelength_sample: float | None = None,
               pixels: mi.UInt32 | None = None) -> CameraSubpaths:
        """``wavelength_sample``, ``pixels``: see :func:`sample_camera_rays` (None: every ray draws its own
        wavelengths; every film sample)."""
        ray, weight, pos = sample_camera_rays(sensor, sampler, spp, wavelength_sample, pixels)
        active = dr.full(mi.Bool, True, dr.width(pos))
        sampler.schedule_state()
        dr.eval(ray, weight, pos)  # kept until the splat: never recompute them from a later sampler state
        args = (scene, sampler, mi.Ray3f(ray), mi.Spectrum(1), 0, active)
        walk = self.walker.run(*args, hide_first_emitters=hide_emitters)
        record = partial(self.walker.record, *args, hide_first_emitters=hide_emitters)
        return CameraSubpaths(position=pos, sensor_weight=weight, wavelengths=ray.wavelengths, walk=walk,
                              record=record)
