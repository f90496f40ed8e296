"""Light segment sampler: first segments from the emitters (``p_L ∝ Le G``), then adjoint-BSDF children."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import drjit as dr
import mitsuba as mi

from .emission import sample_emitter_ray
from .walk import RandomWalk, Vertex


@dataclass
class LightSubpaths:
    """A wavefront of light sub-paths: the emitted rays and the walk that extends them."""

    ray: mi.Ray3f  #: emitted ray (origin on the emitter)
    weight: mi.Spectrum  #: emitted radiance / (position, direction and emitter-selection pdfs)
    emitter: mi.EmitterPtr
    sample2: mi.Point2f  #: the spatial sample ``scene.sample_emitter_ray`` was given (an area light's position)
    walk: Iterator[Vertex]  #: the walk, vertex by vertex (wavefront)
    record: Callable[[Any], None]  #: the same walk with a consumer in its loops (:meth:`RandomWalk.record`)


class LightSegmentSampler:
    def __init__(self, max_depth: int, rr_depth: int, for_pool: bool = False, absorb_delta_lobes: bool = False,
                 delta_chains_only: bool = False, max_segments: int = 0xFFFFFFFF):
        self.walker = RandomWalk(mi.TransportMode.Importance, max_depth, rr_depth, max_segments,
                                 keep_zero_weight=for_pool, absorb_delta_lobes=absorb_delta_lobes,
                                 delta_chains_only=delta_chains_only)

    def sample(self, scene: mi.Scene, sensor: mi.Sensor, sampler: mi.Sampler, count: int,
               wavelengths=None, emitted: Callable | None = None) -> LightSubpaths:
        """``count`` light sub-paths, as ``ptracer`` emits them.

        With ``wavelengths`` (spectral variants), the sub-paths carry these wavelengths instead of those the
        emitters sampled, and the emitted rays are weighted by ``emitted(ray, emitter, sample2, active)``:
        the emitted radiance at those wavelengths over the position and direction densities, where
        ``sample2`` is the spatial sample ``scene.sample_emitter_ray`` was given (docs/maths.md §9). The
        random numbers drawn are the same either way."""
        time = dr.full(mi.Float, sensor.shutter_open(), count)
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wav = sampler.next_1d()
        direction_sample = sampler.next_2d()  # Mitsuba's sample2: an area light's position, as ptracer names it
        position_sample = sampler.next_2d()
        ray, weight, emitter = sample_emitter_ray(scene, time, wav, direction_sample, position_sample,
                                                  dr.full(mi.Bool, True, count))
        if wavelengths is not None:
            ray.wavelengths = wavelengths
            weight = emitted(ray, emitter, direction_sample, dr.full(mi.Bool, True, count))
        active = dr.any(mi.unpolarized_spectrum(weight) != 0)
        args = (scene, sampler, ray, weight, 1, active)
        return LightSubpaths(ray=ray, weight=weight, emitter=emitter, sample2=direction_sample,
                             walk=self.walker.run(*args),
                             record=partial(self.walker.record, *args))
