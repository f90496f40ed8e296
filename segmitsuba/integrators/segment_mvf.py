"""``segment_mvf``: camera segment sampler × recursive MMIS estimation (multi-vertex filtering)."""

from __future__ import annotations

import mitsuba as mi

from .filtering import FilteringIntegrator, parameters


class SegmentMultiVertexFilter(FilteringIntegrator):
    __doc__ = r"""
    Multi-vertex filtering (:monosp:`segment_mvf`)
    -----------------------------------------------

    The camera segment sampler fills one pool of segments per pass; the recursive marginal-MIS estimator
    gathers, for every segment end, the segments that start in the same kernel domain, weighted by the balance
    denominator of every technique that could have produced them (docs/maths.md §4). Biased
    by the kernel (a blur of its size); consistent with ``alpha < 1``.
    """ + parameters(None)

    plugin_name = "segment_mvf"
    uses_camera = True
    uses_light = False


mi.register_integrator("segment_mvf", lambda props: SegmentMultiVertexFilter(props))
