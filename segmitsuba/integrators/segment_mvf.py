"""``segment_mvf``: camera segment sampler × recursive MMIS estimation (multi-vertex filtering)."""

from __future__ import annotations

import mitsuba as mi

from .filtering import FilteringIntegrator


class SegmentMultiVertexFilter(FilteringIntegrator):
    r"""
    Multi-vertex filtering (:monosp:`segment_mvf`)
    -----------------------------------------------

    The camera segment sampler fills one pool of segments per pass; the recursive
    marginal-MIS estimator gathers, for every segment end, the segments that start within the same
    kernel domain, weighted by the balance
    denominator of every technique that could have produced them (shared/design/segment-transport.md §3).
    Biased by the kernel (blur of radius r); consistent with ``alpha < 1``.

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest segment path (sets the ``max_depth - 1`` MMIS iterations). (Default: 8, as the paper)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts (segment vertices only). (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: false)
     * - kernel
       - |string|
       - ``cluster``: jittered voxels split by normal bins, K = 1/A(C) (the paper's choice); ``radius``: a disc
         of radius r around each end, K = 1/(pi r^2). (Default: cluster)
     * - kernel_size
       - |float|
       - Voxel side (cluster) or radius (radius) in world units; 0 derives it from the scene. (Default: 0)
     * - kernel_scale
       - |float|
       - Derived size = this x the median pixel footprint at the first hits. (Default: 4 for cluster, as the
         paper; 2 for radius)
     * - alpha
       - |float|
       - Progressive kernel shrinking over passes, r^2 *= (i + alpha) / (i + 1); 1 keeps it fixed. (Default: 1)
     * - light_ratio
       - |float|
       - Light sub-paths per camera sub-path (the paper's beta). (Default: 0.25 for bdf, 1 for pf)
     * - spp_per_pass
       - |int|
       - Camera samples per pixel in one pass (one pool, one linear system); 0 sizes passes from
         ``memory_budget``. (Default: 0)
     * - memory_budget
       - |float|
       - MiB one pass may use; a pass that cannot fit is refused with a clear error. (Default: 2048)
    """

    plugin_name = "segment_mvf"
    uses_camera = True
    uses_light = False


mi.register_integrator("segment_mvf", lambda props: SegmentMultiVertexFilter(props))
