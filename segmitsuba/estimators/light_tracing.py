"""Light tracing inside a filter's pool: the caustic segments the first camera vertices gather, also
connected to the sensor (docs/maths.md §4.11).

A light segment ``s'`` whose start ``x'`` lies where the camera sees is gathered by the first camera segments
ending near ``x'`` (in its kernel domain): a kernel estimate of what ``x'`` sends toward the camera. Connecting
``x'`` itself to the sensor estimates the same light without the kernel, as ``segment_lt`` (and ``ptracer``)
do. Both estimate one sum over the pool's sources, ``sum_s' h(s') / D(s')``, so any split of each source
between them, ``w(s')`` to the connection and ``1 - w(s')`` to what the first segments gather, counts it once,
provided that the connection takes ``D`` with the camera technique of the first vertex it stands for: a gather
is only made by a camera vertex that ``D`` already counts.

Only segments that arrived through delta lobes (not straight: caustics through glass, mirrors, coatings) are
split. Light techniques and emission alone produce them, and their light is concentrated, so the kernel blurs
it most; straight segments (light scattered by a smooth lobe) are smooth, and gathering them with every camera
sample of the kernel domain beats one splat each (measured: docs/maths.md §4.11).

``w`` is the balance heuristic with which vertex connection and merging weights light tracing against merging
at the first camera vertex: the merge draws about ``n = N_c p_A(x') / K(x')`` camera samples in the kernel
domain of ``x'`` (``N_c`` camera samples, ``p_A`` the area density of a camera sample's first hit, ``K`` the
kernel), the connection one, so ``w = 1 / (1 + c n)``, with ``c`` measured. ``w`` depends on ``x'`` alone (the
sensor's density is taken at its lens centre), never on the random numbers of either estimate, so the split
stays exact.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..population import CAMERA, LIGHT, SegmentPool
from .mmis import EdgeSubset, MMISEstimator, MMISSystem
from .sequential import _connect_sensor

#: ``c`` of the weight (``light_tracing_balance``), measured at 256x256 (docs/maths.md §4.11)
LIGHT_TRACING_BALANCE = 0.05


def light_tracing_sources(pool: SegmentPool, system: MMISSystem) -> mi.Bool:
    """Caustic segments that a first camera segment ending at their start would gather: light sources of the
    pool that contain a delta vertex (not straight), whose start is not a private glossy vertex (which gathers
    nothing, docs/maths.md §4.8)."""
    mask = (pool.kind == LIGHT) & system.gatherable & (system.denominator > 0) & ~pool.straight
    if system.glossy is not None:
        mask &= ~system.glossy  # a light segment's walk surface is its start x
    return mask


def split_first_gather(scene: mi.Scene, sensor: mi.Sensor, estimator: MMISEstimator, pool: SegmentPool,
                       system: MMISSystem, radiance: mi.Spectrum, emitted: mi.Spectrum, direct, camera_samples: int,
                       block: mi.ImageBlock, scale: mi.Float, seed: int, balance: float = LIGHT_TRACING_BALANCE,
                       splat_weight: mi.Spectrum | None = None, first_q: float = 1.0,
                       first_edges: EdgeSubset | None = None) -> mi.Spectrum:
    """Splat the connection share ``w`` of every caustic source into ``block`` and return ``radiance`` (the
    solve's result) with the first straight camera segments' gather of those shares, ``T (A (w c))``, taken
    out. ``c``: what each source carried into the solve's last iteration (``MMISEstimator.previous``, less the
    covered emission that the sharp rows of ``direct`` no longer gather, docs/maths.md §4.7); ``scale``: the
    film weight of one pool's splat; ``balance``: ``c`` of the weight; ``splat_weight``: the camera lanes'
    wavelength weight (spectral); ``first_q``: the camera walks' survival probability at their first vertex
    (the technique density of the gatherer that a connection stands for); ``first_edges``: the edges of the
    first camera segments (:func:`~segmitsuba.estimators.mmis.edge_subset`), the only queries read here."""
    sources = light_tracing_sources(pool, system)
    if not dr.any(sources):
        return radiance
    carried = estimator.previous
    if direct is not None:
        carried = carried - pool.chain * emitted * direct.covered
    idx = dr.compress(sources)
    surf = pool.end_surface("x", idx, True)
    wx = dr.gather(mi.Vector3f, pool.wx, idx)
    si = surf.interaction(wx)
    # the weight from the lens centre: a function of x' alone
    ds0, sw0 = sensor.sample_direction(si, mi.Point2f(0.5), True)
    ds, sw = ds0, sw0
    if sensor.needs_aperture_sample():
        rng = mi.PCG32()
        rng.seed(dr.opaque(mi.UInt64, ((seed & 0xFFFFFFFF) * 0x9E3779B97F4A7C15 + 0x61C88647) & 0xFFFFFFFFFFFFFFFF),
                 mi.UInt64(idx))
        ds, sw = sensor.sample_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()), True)
    area = mi.unpolarized_spectrum(sw0)[0] * dr.abs(dr.dot(si.n, ds0.d))  # p_A(x') per camera sample over the image
    merged = dr.opaque(mi.Float, float(camera_samples)) * area / dr.gather(mi.Float, system.source_kernel, idx)
    w = dr.select(ds0.pdf > 0, dr.rcp(1.0 + dr.opaque(mi.Float, balance) * merged), 0.0)
    w = dr.select(dr.isfinite(w), w, 0.0)

    si.wi = si.to_local(ds.d)
    f, pdf = si.bsdf().eval_pdf(estimator.ctx_radiance, si, si.to_local(wx), True)
    # D of the source with the camera technique of one more first vertex at x': the gatherer the connection
    # stands for. A gather is only made by a camera vertex that D already counts, which makes it exact on
    # average (E[X g(X)] = n E[g(X + 1)], docs/maths.md §4.11); a connection made with D alone would count the
    # source with the weight it has where no camera vertex is near, too bright where few are.
    # The camera technique makes no segment through the delta lobe of a mixed vertex (absorbed) nor from a
    # delta emitter, and photon filtering has none.
    k = dr.gather(mi.Float, system.source_kernel, idx)
    camera = any(t.name == "camera" for t in estimator.techniques)
    made = ~dr.gather(mi.Bool, pool.absorbed, idx) & ~dr.gather(mi.Bool, pool.delta_emit, idx)
    extra = dr.select(made, dr.opaque(mi.Float, first_q if camera else 0.0) * k * pdf, 0.0)
    denominator = dr.gather(mi.Float, system.denominator, idx) + extra
    value = dr.gather(mi.Spectrum, carried, idx) / denominator
    # f (radiance mode) holds the cosine toward the light; the camera sees dA(x') at the cosine toward it
    weight = sw * dr.abs(dr.dot(si.n, ds.d)) * scale * w * value
    if splat_weight is not None:
        weight *= splat_weight
    _connect_sensor(scene, sensor, block, si, ds, weight, f, 0.0, (w > 0) & (ds.pdf > 0))

    share = dr.zeros(mi.Float, pool.size)
    dr.scatter(share, w, idx)
    given = estimator.gather(system, pool, share * carried, first_edges)
    # the rows that see x' directly: first segments with no delta vertex inside (sharp rows, with `direct`)
    gave = (pool.kind == CAMERA) & (pool.index == 0) & pool.straight
    if direct is not None:
        gave &= direct.rows
    radiance = dr.select(gave, radiance - pool.chain * given, radiance)
    dr.eval(radiance)
    return radiance
