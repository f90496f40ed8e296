"""``segment_pf``: light segment sampler × recursive MMIS estimation (photon filtering)."""

from __future__ import annotations

import mitsuba as mi

from .filtering import FilteringIntegrator, parameters


class SegmentPhotonFilter(FilteringIntegrator):
    __doc__ = r"""
    Photon filtering (:monosp:`segment_pf`)
    ----------------------------------------

    The light segment sampler fills one pool of segments per pass (camera segments serve only as queries); the
    recursive marginal-MIS estimator gathers, for every segment end, the segments that start in the same kernel
    domain, weighted by the balance denominator of every technique that could have produced them
    (docs/maths.md §4). Biased by the kernel (a blur of its size); consistent with ``alpha
    < 1``.
    """ + parameters("1", camera_walks=False)

    plugin_name = "segment_pf"
    uses_camera = False
    uses_light = True
    default_light_ratio = 1.0


mi.register_integrator("segment_pf", lambda props: SegmentPhotonFilter(props))
