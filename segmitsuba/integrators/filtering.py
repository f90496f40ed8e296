"""What ``segment_mvf``, ``segment_pf`` and ``segment_bdf`` share: pools, the kernel schedule of the render, and
the sampler x recursive-MMIS plumbing. The three plugins differ only in which samplers fill the pool."""

from __future__ import annotations

import math
import time
import warnings

import drjit as dr
import mitsuba as mi

from .. import KernelSizeWarning, SparsePoolWarning
from ..estimators.bdpt import EmitterTerms
from ..estimators.direct import emitter_samples_suffice, only_delta_emitters, sharp_chain_light, sharp_direct_light
from ..estimators.light_tracing import LIGHT_TRACING_BALANCE, split_first_gather
from ..estimators.mmis import MMISEstimator, edge_subset
from ..estimators.sequential import sensor_connects
from ..film import FilmTarget, film_lattice, film_sample_count, prepare_sampler
from ..population import CAMERA, LIGHT, RecordBuffer, SegmentPool, SegmentRecorder, delta_emitters, record_next_event
from ..references import relmse
from ..samplers.camera import CameraSegmentSampler, sample_camera_rays, sample_sensor_ray
from ..samplers.light import LightSegmentSampler
from ..schedule import kernel_size_at, pass_seed
from .base import PropertyReader, SegmentIntegrator

_COMMON_ROWS = """
    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path in rays, delta bounces included, as Mitsuba's ``path`` counts them; the MMIS solve
         bounds it too (docs/maths.md §4.4). (Default: 8, as the paper)
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
       - Initial voxel side (cluster) or radius (radius) in world units; 0 derives it from the scene.
         (Default: 0)
     * - kernel_scale
       - |float|
       - Derived size = this x the median pixel footprint at the first hits. (Default: 6 for cluster, wider
         than the paper's 4 since direct light at what the camera sees is sampled (docs/maths.md §5.3); in
         ``segment_bdf`` 9 where no BSDF of the scene has a delta lobe, so no caustic can blur, on films of 256
         pixels or more a side; 2 for radius)
     * - direct_light
       - |string|
       - Direct light at what the camera sees (the end of each segment reached from the sensor through delta
         lobes only; docs/maths.md §4.7). ``sampled``: one emitter sample and the walk's own BSDF sample,
         combined by MIS as ``path`` does, unfiltered, with everything else filtered; ``mis``: that emitter
         sample combined by MIS with the gathered emission (smoother under large emitters, more costly);
         ``filtered``: gathered like all other light. (Default: sampled, the fastest to a given error at
         256x256 on every benchmark scene)
     * - direct_samples
       - |int|
       - Emitter samples per sharp vertex with ``direct_light`` ``sampled`` or ``mis``; ``sampled`` adds as many
         BSDF samples (the walk's own is one). The pool is paid once per camera sample, these few rays per
         sample (docs/maths.md §4.7). A lone delta light gets one sample. (Default: 8 with ``sampled``, the best
         common choice by time to error at 256x256 on the benchmark scenes: 4.4x on veach_glossy, 1.7x on
         cornell, no scene slower; 1 with ``mis``, where each sample also evaluates a denominator)
     * - direct_spp
       - |int|
       - With ``direct_light`` ``sampled``: camera samples per pool sample that estimate the direct light at what
         the camera sees (and the emitters it sees) on their own, as ``path`` does, instead of the pool's camera
         samples; the pool gathers the rest (docs/maths.md §4.10). Each is a camera ray, a shadow ray and a BSDF
         ray, far cheaper than a pool sample, and they average highlights and shadow edges inside a pixel's
         footprint. ``direct_samples - 1`` then only sets the final-gathering samples. 0: the pool's camera
         samples take the direct light, ``direct_samples`` per vertex. (Default: derived from the scene with
         ``sampled``: the count that balances the variances and costs of the two parts, measured on two small
         probe pools once per scene and sensor, a power of two from 1 to 64; 0 otherwise)
     * - apart_emitter_samples
       - |int|
       - Emitter samples per vertex of each of those camera samples (one camera ray for several, stratified over
         the choice of emitter and the point on it, docs/maths.md §4.10). (Default: derived from the scene where
         ``direct_spp`` is not 0: the count that balances the variance left by the camera ray against that of the
         emitter samples, per cost, measured with 1 and 4 independent samples on two small probe images once per
         scene and sensor, a power of two from 1 to 16)
     * - alpha
       - |float|
       - Progressive kernel shrinking over the pools of the whole render,
         r_i^2 = r_0^2 prod_{j<i} (j + alpha) / (j + 1) (the paper: 0.67); 1 keeps it fixed. (Default: 0.67)
"""

_GLOSSY_ROW = """\
     * - glossy_vertices
       - |string|
       - Vertices whose BSDF has a glossy lobe and no delta one (rough conductors, rough plastics, ...).
         ``private``: the camera walk continues from them on its own, as ``path`` does, with one emitter sample
         there; they gather nothing and no technique at them makes sources (docs/maths.md §4.8). ``filtered``:
         they gather like any vertex. (Default: private, unless ``direct_light`` is ``filtered``)
     * - final_gather
       - |bool|
       - With private glossy vertices: the ``direct_samples - 1`` extra BSDF samples of a glossy vertex that
         the camera sees also gather the pool's light where they land on a diffuse surface, as many samples of
         what it reflects instead of the walk's one (docs/maths.md §4.9). (Default: true)
     * - next_event_segments
       - |bool|
       - Every camera vertex that continues its walk also takes one emitter sample (visibility tested) that joins
         the pool as a segment carrying emission: every query in its kernel domain gathers it, and its density
         enters the denominator of the emission that straight segments carry, photons from point, spot and
         directional lights included (docs/maths.md §3.5). Not with ``direct_light`` ``mis``. (Default: derived
         from the scene: in ``segment_mvf`` on, 1.0-1.3x less error at 30 s at 256x256 under area lights; in
         ``segment_bdf`` on where the scene has a point, spot or directional light, 2x less error at equal time
         on such scenes at 128x128, and off otherwise, 1.1-1.8x slower to a given error on the five benchmark
         scenes at 256x256)
"""

_LIGHT_RATIO_ROW = """\
     * - light_ratio
       - |float|
       - Light sub-paths per camera sub-path (the paper's beta). (Default: {default})
     * - light_tracing
       - |bool|
       - Light segments that arrive through delta lobes (caustics) where the camera sees them directly are
         also connected to the sensor, unfiltered, and the first camera vertices gather only the rest of them,
         split by the balance heuristic of vertex connection and merging (docs/maths.md §4.11). Sensors that
         cannot be connected to (orthographic) render without it. (Default: true, unless ``direct_light`` is
         ``mis``)
     * - light_tracing_balance
       - |float|
       - ``c`` of that split: a caustic segment goes to the sensor with weight 1 / (1 + c n), n the camera
         samples expected in its kernel domain; 0 connects every one. (Default: 0.05, the best of 0 / 0.015 / 0.05
         / 0.15 by time to error on the caustic scene at 256x256)
"""

_LIGHT_WALKS_ROW = """\
     * - light_walks
       - |string|
       - ``delta_chains``: past their first segment, the light walks keep only segments through a delta vertex
         (caustic chains) and stop where a segment would be straight: the camera walks make those too, and light
         segments in mid-path are where small pools are biased (docs/maths.md §2.5, §8.1). Where no BSDF of the
         scene mixes a delta lobe with a smooth one, the camera walks make every such chain as well, and the light
         walks stop after their emitted segment. ``full``: the paper's whole light walks. (Default: delta_chains)
"""

_PASS_ROWS = """\
     * - spp_per_pass
       - |int|
       - Camera samples per pixel in one pool (one segment population, one linear system); 0 sizes pools
         from the resolution and ``memory_budget`` (up to 4 spp and about 256k camera samples in
         ``segment_bdf``, 128k in the others; where one sample per pixel does not fit, pools of one of 2, 4,
         ... 256 interleaved film lattices each, docs/maths.md §5.7). (Default: 0)
     * - memory_budget
       - |float|
       - MiB one pool may use (about 8.5 KB per camera sample at ``max_depth`` 8): a film whose one sample per
         pixel exceeds it renders in pools of film lattices; ``spp_per_pass`` that cannot fit, or a budget below
         a 256th of a sample per pixel, is refused with a clear error. (Default: 3072)
     * - time_budget
       - |float|
       - Seconds after which no new pool starts within one call (at least one pool runs; pools of film
         lattices stop only between samples per pixel); 0 renders all samples. (Default: 0)

    **A render in several calls.** The kernel shrinks over the pools of the whole render, not of one
    ``mi.render`` call. Before each call of a render split into several, set ``integrator.spp_offset`` to the
    samples per pixel that the earlier calls took (and, in spectral variants, ``integrator.render_seed`` to the
    render's seed, which spreads the pools' wavelengths over the render), and give call ``k`` the seed
    ``segmitsuba.schedule.pass_seed(seed, k)``::

        done = 0
        integrator.render_seed = seed
        for k in range(16):
            integrator.spp_offset = done
            image = mi.render(scene, integrator=integrator, spp=4, seed=pass_seed(seed, k))
            done += 4

    ``segmitsuba.rendering.render_passes``, the command line, ``compare`` and the Dask tasks do this; calls of
    one pool each then draw exactly the pools of one call of all the samples. ``integrator.last_stats`` lists
    every pool of the last call (``pools``: its spp offset, spp, seed and kernel size).

    **Variants.** RGB, mono and spectral. Gathering joins segments of different walks, so in spectral
    variants every segment of a pool carries the same wavelengths: one wavelength sample per pool (from its
    seed) for all of its camera rays, and the light sub-paths take those wavelengths, their emission
    re-weighted as ``segment_bdpt``'s. The shared wavelengths add no bias (averaged over pools), but their
    noise no longer averages over the samples of a pool, only over pools: each pool's image is tinted as a
    whole, most in blue and red (``docs/maths.md`` §10).
"""


def parameters(light_ratio: str | None, camera_walks: bool = True) -> str:
    """A filter plugin's parameter table (``light_ratio``, the text of its default, only for the filters that trace
    light sub-paths, ``glossy_vertices`` only for those whose camera walks go past the first vertex,
    ``light_walks`` only for those with both)."""
    rows = _GLOSSY_ROW if camera_walks else ""
    if light_ratio is not None:
        rows += _LIGHT_RATIO_ROW.format(default=light_ratio) + (_LIGHT_WALKS_ROW if camera_walks else "")
    return _COMMON_ROWS + rows + _PASS_ROWS


#: rough bytes per camera sample and pool segment, for sizing passes from the memory budget
_BYTES_PER_SEGMENT = 220
_BYTES_PER_EDGE = 20
#: edge-list room per segment slot: the radius kernel lists every neighbour (~48); the cluster kernel gathers
#: Lambertian queries through cluster sums and lists only curved and glossy ones (0.3 / 15.8 explicit edges per
#: segment on cornell 256x256 / glossy_occluded 512x512 at the default kernel), with room for the system's
#: per-segment arrays and the solve's rings on delta chains: the estimate is then 9.7 KB per camera sample at
#: max_depth 8, against a measured peak of 8.5 KB on glossy_occluded at 512x512 (2185 MiB, no rings)
_EDGES_PER_SEGMENT = {"radius": 48, "cluster": 32}
#: the solve's rings where segments span several rays (docs/maths.md §4.4): one spectrum per segment and
#: level, ``max_depth + 1`` levels at most
_BYTES_PER_LEVEL = 12
#: camera samples per wavefront of the direct light apart from the pool (docs/maths.md §4.10)
_APART_LANES = 1 << 21
#: the cluster kernel's default width in pixel footprints (docs/maths.md §5.3)
CLUSTER_KERNEL_SCALE = 6.0
#: the cost of one pool segment per camera sample (trace, system, solve) over that of one apart camera sample
#: (docs/maths.md §4.10): 6.3-9.7 on the five benchmark scenes at 256x256 (us per segment / us per apart
#: sample), about their middle
POOL_SEGMENT_COST = 7.5
#: apart samples per pixel of each probe pool, and the most a derived ``direct_spp`` gives
PROBE_DIRECT_SPP = 4
#: the apart samples' Lambertian vertices take the emitter sample alone where that raises their variance by less
#: than this: the time it saves (1.7-1.8x on cornell and on a panel lighting the floor it touches, docs/maths.md
#: §4.10), less a margin
LAMBERTIAN_ALONE_RATIO = 1.5
MAX_DERIVED_DIRECT_SPP = 64
#: the most film lattices one sample per pixel is split into where a pool of all pixels exceeds the memory budget
#: (a 16x16 lattice: a pool then holds every sixteenth column of every sixteenth row)
MAX_POOL_GROUPS = 256
#: the cost of one more emitter sample of an apart camera sample over that of the sample with one
#: (docs/maths.md §4.10): 0.17-0.28 on the five benchmark scenes at 256x256 (time per sample with 1 and 4)
APART_EMITTER_SAMPLE_COST = 0.25
#: the emitter samples per vertex the apart probe compares with one, and the most a derived count gives
PROBE_APART_EMITTER_SAMPLES = 4
MAX_DERIVED_APART_EMITTER_SAMPLES = 16
_PROBE_SEED = 0x51A7E
_PROBE_FLOOR = 0.5


#: the share of sparse queries (:meth:`MMISSystem.sparse_share`) above which ``segment_bdf`` warns
SPARSE_WARN_SHARE = 0.5


def _probed(cache: dict, scene: mi.Scene, sensor: mi.Sensor, probe) -> dict:
    """``probe(scene, sensor)``, once per scene, sensor and film crop (the entry of ``cache``)."""
    film = sensor.film()
    key = (id(scene), id(sensor), tuple(film.crop_size()), tuple(film.crop_offset()))
    if key not in cache:
        cache[key] = probe(scene, sensor)
    return cache[key]


def _pool_counters() -> dict:
    """What :meth:`FilteringIntegrator._render_pool` adds up over the pools of one call."""
    return {"segments": 0, "camera_segments": 0, "light_segments": 0, "light_paths": 0, "edges": 0, "lumped": 0,
            "time_trace": 0.0, "time_camera_walks": 0.0, "time_light_walks": 0.0, "time_system": 0.0,
            "time_solve": 0.0, "time_rows": 0.0, "time_apart": 0.0}


def _bsdf_has(scene: mi.Scene, *flags: mi.BSDFFlags) -> bool:
    """Whether the BSDF of a shape of the scene has every lobe of ``flags``."""
    return any(shape.bsdf() is not None and all(mi.has_flag(shape.bsdf().flags(), f) for f in flags)
               for shape in scene.shapes())


def has_delta_bsdf(scene: mi.Scene) -> bool:
    """Whether a BSDF of the scene has a delta lobe (mirrors, glass, smooth coatings): where caustics can form."""
    return _bsdf_has(scene, mi.BSDFFlags.Delta)


def has_mixed_bsdf(scene: mi.Scene) -> bool:
    """Whether a BSDF of the scene has a delta lobe and a smooth one (``plastic``'s coating, a ``blendbsdf`` of
    a mirror and a diffuse layer, a ``mask``): where camera walks drop what leaves the delta lobe and light walks
    carry it (docs/maths.md §2.3, §2.5)."""
    return _bsdf_has(scene, mi.BSDFFlags.Delta, mi.BSDFFlags.Smooth)


def check_image_sensor(plugin: str, sensor: mi.Sensor) -> None:
    """The filters gather the camera samples of an image, whose pixel footprints size their kernels: refuse
    sensors that measure one ray, one surface or one direction (``radiancemeter``, ``irradiancemeter``,
    ``distant``). Their pools would be a few samples of one pixel: on a radiance meter at 512 spp they
    rendered 0.09-0.8x of ``path``, at 16k spp still 0.92-0.98x (docs/maths.md §5.3)."""
    if isinstance(sensor, mi.ProjectiveCamera) or sensor.class_name() == "BatchSensor":
        return
    raise RuntimeError(
        f"{plugin}: filters gather the camera samples of an image (perspective, thinlens, orthographic or batch "
        f"sensors), not those of a {sensor.class_name()}, which measures one pixel. Use segment_pt or "
        "segment_bdpt, which render it.")


def pixel_footprint(scene: mi.Scene, sensor: mi.Sensor, grid: int = 32) -> float:
    """Median world-space distance between the first hits of neighbouring pixel centres."""
    film = sensor.film()
    size = film.crop_size()
    i = dr.arange(mi.UInt32, grid * grid)
    u = (mi.Float(i % grid) + 0.5) / grid
    v = (mi.Float(i // grid) + 0.5) / grid
    du = mi.Float(1.0 / size[0])
    time_ = mi.Float(sensor.shutter_open())
    hits = []
    for off in (0.0, 1.0):
        ray, _ = sample_sensor_ray(sensor, time_, mi.Float(0.5), mi.Point2f(u + off * du, v), mi.Point2f(0.5))
        hits.append(scene.ray_intersect(ray))
    a, b = hits
    both = a.is_valid() & b.is_valid()
    d = dr.norm(a.p - b.p)
    import numpy as np

    values = np.array(dr.select(both, d, -1.0))
    values = values[(values > 0) & np.isfinite(values)]
    if len(values) == 0:
        extent = scene.bbox().extents()
        return float(dr.max(extent)) / max(size) if scene.bbox().valid() else 1.0
    return float(np.median(values))


#: the golden-ratio conjugate: the step of the pools' Kronecker sequence of wavelength samples
_GOLDEN = 0.6180339887498949


def pool_wavelength_sample(render_seed: int, pool_index: float = 0.0) -> float:
    """The one wavelength sample in [0, 1) that every segment of a pool shares (spectral variants,
    docs/maths.md §10.4): for the pool at ``pool_index`` (its spp offset in the render over the render's pool
    size) of the render with seed ``render_seed``, ``u = frac(h + pool_index · φ / W)``, ``h`` a 32-bit hash of
    the seed and ``W`` the wavelengths per lane. A lane's W wavelengths are those of ``u + k/W``, so what matters
    is ``frac(W u) = frac(W h + pool_index · φ)``: a Kronecker sequence, randomly rotated. Each pool's ``u`` is
    uniform (no bias), and the pools of a render cover the spectrum evenly whichever way it is split into
    calls, as they are positions in the render."""
    h = (render_seed * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    h ^= h >> 16
    lanes = dr.size_v(mi.Spectrum) if mi.is_spectral else 1
    u = ((h >> 8) * 2.0**-24 + pool_index * _GOLDEN / lanes) % 1.0
    return min(u, 1.0 - 2.0**-24)  # rounding must not reach 1


class FilteringIntegrator(SegmentIntegrator):
    """Sampler(s) x recursive MMIS. Subclasses set ``uses_camera`` / ``uses_light``."""

    uses_camera = True
    uses_light = True
    default_max_depth = 8  # the paper's path depth
    #: the default light_ratio of the filters that trace light sub-paths
    default_light_ratio = 0.25
    #: the default light_ratio where a BSDF of the scene has a delta lobe, so that light walks carry caustic chains
    #: (None: :attr:`default_light_ratio` everywhere; docs/maths.md §4.6)
    light_ratio_with_delta: float | None = None
    #: camera samples a pool holds at most by default (docs/maths.md §5.6): 4-spp pools at 256x256 were
    #: measured with segment_bdf only; photon pools list a glossy receiver's photons one by one, so their cost
    #: grows with the square of the population (segment_pf on glossy_occluded: 8 spp in 30 s at 4 spp per pool)
    pool_camera_samples = 131072
    #: the cluster kernel's width in pixel footprints where no BSDF has a delta lobe (docs/maths.md §5.3)
    kernel_scale_without_delta = CLUSTER_KERNEL_SCALE
    #: light-tracing splats follow the camera samples' convention at the film border (FilmTarget)
    normalize_light = True

    @property
    def uses_light_paths(self) -> bool:  # type: ignore[override]
        return self.uses_light

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        read = PropertyReader(self.plugin_name, props)
        if self.max_depth < 1:
            raise ValueError(f"{self.plugin_name}: property 'max_depth' must be >= 1 for a filtering "
                             f"estimator (it sets the levels of the MMIS solve), got {self.max_depth}")
        self.kernel = read.choice("kernel", "cluster", ("cluster", "radius"))
        # world units (voxel side or disc radius); 0: derived from the pixel footprint at the first hits
        self.kernel_size = read.real("kernel_size", 0.0, minimum=0.0)
        #: None: derived from the scene (:meth:`kernel_scale_for`)
        self.kernel_scale: float | None = read.real("kernel_scale", 0.0 if self.kernel == "cluster" else 2.0,
                                                    minimum=0.0, exclusive_min=True) or None
        self.direct_light = read.choice("direct_light", "sampled", ("sampled", "mis", "filtered"))
        # each `mis` sample also evaluates a denominator, so `mis` takes one unless asked
        self.direct_samples = read.integer("direct_samples", 8 if self.direct_light == "sampled" else 1, minimum=1,
                                           maximum=1024)
        #: None: derived from the scene (:meth:`direct_spp_for`)
        self.direct_spp: int | None = read.integer("direct_spp", -1 if self.direct_light == "sampled" else 0,
                                                   minimum=0, maximum=1024)
        if self.direct_spp == -1:
            self.direct_spp = None
        self._derived_direct_spp: dict[tuple, dict] = {}
        self._lambertian_alone: dict[tuple, dict] = {}
        #: None: derived from the scene (:meth:`apart_emitter_samples_for`)
        self.apart_emitter_samples: int | None = read.integer("apart_emitter_samples", -1, minimum=1,
                                                              maximum=1024)
        if self.apart_emitter_samples == -1:
            self.apart_emitter_samples = None
        elif self.direct_spp == 0:
            raise ValueError(f"{self.plugin_name}: apart_emitter_samples={self.apart_emitter_samples} sets the emitter "
                             "samples of the camera samples of direct light apart from the pool, which direct_spp=0 "
                             f"(direct_light={self.direct_light!r}) does not take; leave it out or let direct_spp "
                             "be derived")
        self._derived_apart_emitter_samples: dict[tuple, dict] = {}
        if self.direct_spp and self.direct_light != "sampled":
            raise ValueError(f"{self.plugin_name}: direct_spp={self.direct_spp} samples the direct light at what "
                             "the camera sees apart from the pool, which only direct_light='sampled' does; got "
                             f"direct_light={self.direct_light!r}")
        self.light_tracing = False
        self.light_tracing_balance = LIGHT_TRACING_BALANCE
        if self.uses_light:
            self.light_tracing = read.boolean("light_tracing", self.direct_light != "mis")
            self.light_tracing_balance = read.real("light_tracing_balance", LIGHT_TRACING_BALANCE, minimum=0.0)
            if self.light_tracing and self.direct_light == "mis":
                raise ValueError(f"{self.plugin_name}: light_tracing splits what the first camera vertices gather, "
                                 "which direct_light='mis' weights against its emitter samples; use "
                                 "direct_light='sampled' or 'filtered', or light_tracing=false")
        self.alpha = read.real("alpha", 0.67, minimum=0.0, maximum=1.0, exclusive_min=True)
        # camera walks that stop at their first vertex (no camera technique) have no continuation to carry
        # what leaves a glossy vertex
        self.glossy_vertices = "filtered"
        if self.uses_camera:
            self.glossy_vertices = read.choice("glossy_vertices",
                                               "filtered" if self.direct_light == "filtered" else "private",
                                               ("private", "filtered"))
            if self.glossy_vertices == "private" and self.direct_light == "filtered":
                raise ValueError(f"{self.plugin_name}: glossy_vertices='private' samples direct light at glossy "
                                 "vertices (nothing else reaches them from delta lights), which "
                                 "direct_light='filtered' turns off; use direct_light='sampled' or 'mis', or "
                                 "glossy_vertices='filtered'")
        private_glossy = self.glossy_vertices == "private"
        self.final_gather = read.boolean("final_gather", True) if self.uses_camera else False
        #: one emitter sample per camera technique, in the pool (docs/maths.md §3.5); None: derived from the scene
        #: (:meth:`next_event_for`)
        self.next_event_segments: bool | None = (read.boolean("next_event_segments", None) if self.uses_camera
                                                 else False)
        if self.next_event_segments and self.direct_light == "mis":
            raise ValueError(f"{self.plugin_name}: next_event_segments puts the emitter samples in the pool's "
                             "denominators, which direct_light='mis' also weights its own samples against; use "
                             "direct_light='sampled' or 'filtered', or next_event_segments=false")
        #: None: derived from the scene (:meth:`light_ratio_for`)
        self.light_ratio: float | None = 0.0
        if self.uses_light:
            self.light_ratio = (read.real("light_ratio", 0.0, minimum=0.0, exclusive_min=True)
                                if "light_ratio" in props else None)
        self.spp_per_pass = read.integer("spp_per_pass", 0, minimum=0)
        self.memory_budget = read.real("memory_budget", 3072.0, minimum=0.0, exclusive_min=True)  # MiB
        self.time_budget = read.real("time_budget", 0.0, minimum=0.0)  # seconds; 0: render all of spp
        #: samples per pixel that earlier calls of the same render took (see the plugin docstring)
        self.spp_offset = 0
        #: seed of the whole render (None: the call's seed), which places each pool's wavelengths (spectral)
        self.render_seed: int | None = None
        self.last_stats: dict = {}
        self._warned_sparse = False
        self._warned_kernel = False
        # Delta lobes of mixed BSDFs (docs/maths.md §2.3). Where light walks exist, they carry what leaves such a
        # lobe to the next vertex as one generalized segment (no camera technique produces it), and camera walks
        # follow the lobe only on the sharp chain that the pixel sees. Camera walks that stop at their first
        # vertex still follow it there; camera-only pools follow it everywhere (private segments).
        stops = not self.uses_camera
        self.camera_sampler = CameraSegmentSampler(self.depth_limit, self.rr_depth,
                                                   max_segments=1 if stops else 0xFFFFFFFF, for_pool=True,
                                                   follow_delta_lobes=stops, drop_delta_lobes=self.uses_light,
                                                   private_glossy=private_glossy)
        # Past their first segment, light walks that camera walks accompany need only carry what those cannot
        # continue: delta chains (docs/maths.md §2.5).
        self.light_walks = "full"
        if self.uses_light and self.uses_camera:
            self.light_walks = read.choice("light_walks", "delta_chains", ("delta_chains", "full"))
        #: past their first segment the light walks keep only delta chains (docs/maths.md §2.5)
        self.light_delta_chains = self.light_walks == "delta_chains"
        self.light_sampler = LightSegmentSampler(self.depth_limit, self.rr_depth, for_pool=True,
                                                 absorb_delta_lobes=self.uses_light,
                                                 delta_chains_only=self.light_delta_chains)
        #: where no BSDF mixes a delta lobe with a smooth one, light walks that keep only delta chains past their
        #: first segment keep none that the camera walks do not make: they stop after their emitted segment
        #: (docs/maths.md §2.5)
        self.emitted_light_sampler = LightSegmentSampler(
            self.depth_limit, self.rr_depth, for_pool=True, absorb_delta_lobes=self.uses_light,
            delta_chains_only=True, max_segments=1) if self.light_delta_chains else None

    # -- the render's schedule ---------------------------------------------------------------------------

    def _bytes_per_sample(self, next_event: bool, light_ratio: float) -> float:
        """The memory estimate of one camera sample's share of a pool: its records (``light_ratio`` light walks per
        camera walk, a next-event record per camera record at most), their edges and the solve's rings."""
        records = 1 + light_ratio + (1 if next_event else 0)
        return records * self.max_depth * (_BYTES_PER_SEGMENT + _EDGES_PER_SEGMENT[self.kernel] * _BYTES_PER_EDGE
                                            + (self.max_depth + 1) * _BYTES_PER_LEVEL)

    def light_ratio_for(self, scene: mi.Scene, delta: bool | None = None) -> float:
        """``light_ratio``, or derived from the scene (docs/maths.md §4.6): :attr:`light_ratio_with_delta` where a
        BSDF of the scene has a delta lobe (light walks carry the caustic chains that camera walks rarely
        continue), :attr:`default_light_ratio` elsewhere (where light walks keep only delta chains, they are then
        emitted segments alone). 0 without light sub-paths. ``delta``: :func:`has_delta_bsdf` of the scene, where
        the caller has it (None: looked up)."""
        if self.light_ratio is not None:
            return self.light_ratio
        if self.light_ratio_with_delta is not None and (has_delta_bsdf(scene) if delta is None else delta):
            return self.light_ratio_with_delta
        return self.default_light_ratio

    def first_survival(self) -> float:
        """The camera walks' survival probability at their first vertex: 1 where they try to continue from it
        (Russian roulette starts at ``rr_depth`` >= 1), 0 where ``max_depth`` stops them there."""
        return 1.0 if self.depth_limit > 1 else 0.0

    def next_event_for(self, scene: mi.Scene, pixels: int) -> bool:
        """``next_event_segments``, or derived from the scene (docs/maths.md §3.5), where a pool of one sample per
        pixel with them fits ``memory_budget``: in camera-only pools always (no emission technique carries the
        light of emitters past what the camera sees, only BSDF samples that hit them); with light sub-paths where
        a point, spot or directional light is in the scene (photons alone carry its light, noisily), and not under
        area and environment lights, where they cost more than they gain at equal time (README, twelfth run)."""
        if self.next_event_segments is not None:
            return self.next_event_segments
        if not self.uses_camera or self.direct_light == "mis" or not scene.emitters():
            return False
        if self.uses_light and not delta_emitters(scene):
            return False
        return self.memory_budget * 2**20 >= pixels * self._bytes_per_sample(True, self.light_ratio_for(scene))

    def pool_spp(self, pixels: int, next_event: bool, light_ratio: float) -> int:
        """Samples per pixel of one pool at ``pixels`` film samples: a property of the render (resolution,
        ``spp_per_pass``, ``memory_budget``, whether next-event segments join the pools, the light sub-paths per
        camera sub-path), never of one call, so that the kernel schedule is too."""
        per_sample = self._bytes_per_sample(next_event, light_ratio)
        fit = int(self.memory_budget * 2**20 // (pixels * per_sample))
        if self.spp_per_pass:
            if self.spp_per_pass > fit:
                raise MemoryError(
                    f"{self.plugin_name}: spp_per_pass={self.spp_per_pass} needs about "
                    f"{pixels * per_sample * self.spp_per_pass / 2**20:.0f} MiB, more than memory_budget="
                    f"{self.memory_budget:g} MiB")
            return self.spp_per_pass
        # Up to 4 spp and pool_camera_samples per pool, measured (docs/maths.md §5.6); below one sample per pixel,
        # pools of part of the pixels (pool_groups)
        return max(1, min(fit, 4, self.pool_camera_samples // max(pixels, 1)))

    def pool_groups(self, pixels: int, next_event: bool, light_ratio: float) -> int:
        """Into how many film lattices (:func:`~segmitsuba.film.film_lattice`) one sample per pixel is split, a
        pool each (docs/maths.md §5.7): 1 where a pool of every pixel fits ``memory_budget`` (or
        ``spp_per_pass`` is set), else the fewest, a power of two, whose pools fit. A property of the render, as
        :meth:`pool_spp`."""
        need = pixels * self._bytes_per_sample(next_event, light_ratio)
        budget = self.memory_budget * 2**20
        if need <= budget or self.spp_per_pass:
            return 1
        groups = 1 << math.ceil(math.log2(need / budget))
        if groups > MAX_POOL_GROUPS:
            raise MemoryError(
                f"{self.plugin_name}: memory_budget={self.memory_budget:g} MiB is too small for a pool of "
                f"1/{MAX_POOL_GROUPS} of the {pixels} pixels (one sample per pixel needs about {need / 2**20:.0f} "
                f"MiB); raise it or lower the resolution or max_depth")
        return groups

    def initial_kernel_size(self, scene: mi.Scene, sensor: mi.Sensor, groups: int = 1) -> float:
        """r_0: ``kernel_size``, or ``kernel_scale`` x the median pixel footprint (deterministic, so every call
        and every worker of a render derives the same value); with pools of one of ``groups`` film lattices
        (:meth:`pool_groups`), x the lattice's spacing sqrt(groups), so that a kernel domain holds as many of a
        pool's camera samples as at one sample per pixel (docs/maths.md §5.7)."""
        if self.kernel_size:
            return self.kernel_size
        return self.kernel_scale_for(scene, sensor) * pixel_footprint(scene, sensor) * math.sqrt(groups)

    def kernel_scale_for(self, scene: mi.Scene, sensor: mi.Sensor) -> float:
        """``kernel_scale``, or the cluster kernel's default (docs/maths.md §5.3): 6, or
        :attr:`kernel_scale_without_delta` where no BSDF has a delta lobe (no caustic for a wider kernel to blur)
        and the film is at least 256 pixels on its shorter side (where that was measured; on a 32x32 film nine
        pixels are over a quarter of the image)."""
        if self.kernel_scale is not None:
            return self.kernel_scale
        if min(sensor.film().crop_size()) < 256:
            return CLUSTER_KERNEL_SCALE
        return CLUSTER_KERNEL_SCALE if has_delta_bsdf(scene) else self.kernel_scale_without_delta

    def connects(self, sensor: mi.Sensor) -> bool:
        """Whether caustic segments also go to the sensor (docs/maths.md §4.11): only where a gather precedes
        the last iteration and the sensor can be connected to."""
        return self.light_tracing and self.max_depth > 1 and sensor_connects(sensor)

    def direct_spp_for(self, scene: mi.Scene, sensor: mi.Sensor) -> int:
        """``direct_spp``, or the count derived from the scene (:meth:`probe_direct_spp`), once per scene,
        sensor and film: every call of a render through this integrator takes the same count, and the probe is
        deterministic, so other workers derive it too."""
        if self.direct_spp is not None:
            return self.direct_spp
        return _probed(self._derived_direct_spp, scene, sensor, self.probe_direct_spp)["direct_spp"]

    def lambertian_alone_for(self, scene: mi.Scene, sensor: mi.Sensor) -> bool:
        """Whether the apart samples' Lambertian vertices take the emitter sample alone (docs/maths.md §4.10):
        never where :func:`~segmitsuba.estimators.direct.emitter_samples_suffice` does not hold, else as
        :meth:`probe_lambertian_alone` finds, once per scene, sensor and film (deterministic, as the count)."""
        if not emitter_samples_suffice(scene):
            return False
        if only_delta_emitters(scene):
            return True  # a BSDF sample finds no emission at all: nothing to weigh
        return _probed(self._lambertian_alone, scene, sensor, self.probe_lambertian_alone)["alone"]

    def _apart_probe_variance(self, scene: mi.Scene, sensor: mi.Sensor, seed: int, lambertian_alone: bool | None,
                              emitter_samples: int, stratified: bool = True) -> float:
        """The variance of an image of :data:`PROBE_DIRECT_SPP` apart samples per pixel (relative to each pixel's
        value, floored as :meth:`probe_direct_spp` floors it): half the relative squared difference of two
        independent ones at the fixed seeds ``pass_seed(seed, 0)`` and ``pass_seed(seed, 1)``."""
        import numpy as np

        film = sensor.film()
        images = []
        for i in range(2):
            target = FilmTarget(film, 1, normalize_light=self.normalize_light)
            self._render_apart(scene, sensor, target, PROBE_DIRECT_SPP, pass_seed(seed, i), lambertian_alone,
                               emitter_samples, stratified)
            images.append(np.array(target.develop_apart()[1], dtype=np.float64))
        film.prepare([])  # the probe developed through the film: leave it empty for the render
        image = (images[0] + images[1]) / 2
        floor = (_PROBE_FLOOR * max(float(image.mean()), 1e-30)) ** 2
        return relmse(images[0], images[1], image, floor) / 2

    def probe_lambertian_alone(self, scene: mi.Scene, sensor: mi.Sensor) -> dict:
        """Two independent images of :data:`PROBE_DIRECT_SPP` apart samples per pixel at fixed seeds, with both
        samples at Lambertian vertices and with the emitter sample alone: alone where its variance (relative, as
        :meth:`probe_direct_spp` measures it) is at most :data:`LAMBERTIAN_ALONE_RATIO` times the other's."""
        t0 = time.perf_counter()
        variance = {alone: self._apart_probe_variance(scene, sensor, _PROBE_SEED ^ 0x1A5, alone, 1)
                    for alone in (False, True)}
        return {"alone": bool(variance[True] <= LAMBERTIAN_ALONE_RATIO * variance[False]),
                "v_both": variance[False], "v_alone": variance[True], "seconds": time.perf_counter() - t0}

    def apart_emitter_samples_for(self, scene: mi.Scene, sensor: mi.Sensor) -> int:
        """``apart_emitter_samples``, or the count derived from the scene (:meth:`probe_apart_emitter_samples`),
        once per scene, sensor and film (deterministic, as ``direct_spp``)."""
        if self.apart_emitter_samples is not None:
            return self.apart_emitter_samples
        return _probed(self._derived_apart_emitter_samples, scene, sensor,
                       self.probe_apart_emitter_samples)["emitter_samples"]

    def probe_apart_emitter_samples(self, scene: mi.Scene, sensor: mi.Sensor) -> dict:
        """The emitter samples per vertex of the apart samples (docs/maths.md §4.10). Their variance per camera
        sample is ``v(k) = v_a + v_b / k``: ``v_a`` what the camera ray leaves (the pixel's footprint, the BSDF
        sample), ``v_b`` the emitter samples'; measured with 1 and :data:`PROBE_APART_EMITTER_SAMPLES` samples on
        two independent images each of :data:`PROBE_DIRECT_SPP` apart samples per pixel at fixed seeds. With the
        cost ``1 + c (k - 1)`` per camera sample (``c``: :data:`APART_EMITTER_SAMPLE_COST`, counted, not timed, so
        that every machine derives the same count), ``v(k)`` times the cost is least at
        ``k* = sqrt(v_b (1 - c) / (v_a c))``, rounded to a power of two in 1 ..
        :data:`MAX_DERIVED_APART_EMITTER_SAMPLES`. Returns the count and what it came from."""
        import numpy as np

        t0 = time.perf_counter()
        # independent samples, whose variance is v_a + v_b / k; the render stratifies them, which can only lower
        # it (the model does not hold for stratified ones: on veach_glossy their v_4 is below v_1 / 4)
        variance = {k: PROBE_DIRECT_SPP * self._apart_probe_variance(scene, sensor, _PROBE_SEED ^ 0x5E3, None, k,
                                                                     stratified=False)
                    for k in (1, PROBE_APART_EMITTER_SAMPLES)}
        m, c = PROBE_APART_EMITTER_SAMPLES, APART_EMITTER_SAMPLE_COST
        v_b = max(variance[1] - variance[m], 0.0) * m / (m - 1)
        v_a = max(variance[1] - v_b, 0.0)
        if v_b <= 0:
            k = 1
        elif v_a <= 0:
            k = MAX_DERIVED_APART_EMITTER_SAMPLES
        else:
            best = (v_b * (1 - c) / (v_a * c)) ** 0.5
            k = min(2 ** round(np.log2(max(best, 1.0))), MAX_DERIVED_APART_EMITTER_SAMPLES)
        return {"emitter_samples": int(k), "v_1": variance[1], f"v_{m}": variance[m], "v_camera": v_a,
                "v_emitter": v_b, "seconds": time.perf_counter() - t0}

    def probe_direct_spp(self, scene: mi.Scene, sensor: mi.Sensor) -> dict:
        """The apart samples per pool sample that balance the two parts of the image (docs/maths.md §4.10):
        ``k* = sqrt((v_sharp / c_sharp) / (v_rest / c_pool))``, from two independent one-spp pools of the render's
        first kernel at fixed seeds, each with :data:`PROBE_DIRECT_SPP` apart samples per pixel. The variances
        per sample are the relative squared differences of the two images of each part (relative to the
        pixel's value, floored as relMSE floors it); the cost ratio is :data:`POOL_SEGMENT_COST` per pool segment
        per camera sample, counted, not timed, so that the count is the same on every machine. Rounded to a
        power of two in 1 .. :data:`MAX_DERIVED_DIRECT_SPP`. Returns the count and what it came from."""
        import numpy as np

        t0 = time.perf_counter()
        film = sensor.film()
        pixels = film_sample_count(film)
        next_event = self.next_event_for(scene, pixels)
        # pools as the render's first: of one film lattice where one sample per pixel does not fit (the variances
        # are then means over the film in which the other lattices' pixels count 0 in both images: their ratio,
        # which sets the count, stays)
        groups = self.pool_groups(pixels, next_event, self.light_ratio_for(scene))
        lattice = film_lattice(film, groups, 0) if groups > 1 else None
        n_cam = pixels if lattice is None else dr.width(lattice)
        r0 = self.initial_kernel_size(scene, sensor, groups)
        self._check_kernel_size(scene, sensor, r0)
        connect = self.connects(sensor)
        stats = _pool_counters()
        parts = []
        for i in range(2):
            target = FilmTarget(film, 1, normalize_light=self.normalize_light)
            wav = pool_wavelength_sample(_PROBE_SEED, i / 2) if mi.is_spectral else None
            self._render_pool(scene, sensor, target, 1, pass_seed(_PROBE_SEED, i), r0, stats, wav, connect,
                              PROBE_DIRECT_SPP, next_event=next_event, pixels=lattice)
            parts.append([np.array(image, dtype=np.float64) for image in target.develop_apart()])
        film.prepare([])  # the probe developed through the film: leave it empty for the render
        (rest_a, sharp_a), (rest_b, sharp_b) = parts
        image = (rest_a + rest_b + sharp_a + sharp_b) / 2
        # relative to each pixel's value, floored at a fraction of the image's mean as relMSE is at ~0.1
        floor = (_PROBE_FLOOR * max(float(image.mean()), 1e-30)) ** 2
        v_rest = relmse(rest_a, rest_b, image, floor) / 2
        v_sharp = PROBE_DIRECT_SPP * relmse(sharp_a, sharp_b, image, floor) / 2
        # c_pool / c_sharp, an apart sample's emitter samples counted (APART_EMITTER_SAMPLE_COST)
        split = self.apart_emitter_samples_for(scene, sensor)
        cost_ratio = POOL_SEGMENT_COST * stats["segments"] / (2 * n_cam) / (1 + APART_EMITTER_SAMPLE_COST * (split - 1))
        if v_sharp <= 0:
            k = 1
        elif v_rest <= 0:
            k = MAX_DERIVED_DIRECT_SPP
        else:
            best = (v_sharp / v_rest * cost_ratio) ** 0.5
            k = min(2 ** round(np.log2(max(best, 1.0))), MAX_DERIVED_DIRECT_SPP)
        return {"direct_spp": k, "v_sharp": v_sharp, "v_rest": v_rest, "cost_ratio": cost_ratio,
                "seconds": time.perf_counter() - t0}

    # -- rendering ----------------------------------------------------------------------------------------

    def render_samples(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, seed: int, spp: int) -> None:
        check_image_sensor(self.plugin_name, sensor)
        pixels = film_sample_count(target.film)
        next_event = self.next_event_for(scene, pixels)
        light_ratio = self.light_ratio_for(scene)
        pool_spp = self.pool_spp(pixels, next_event, light_ratio)
        groups = self.pool_groups(pixels, next_event, light_ratio)
        r0 = self.initial_kernel_size(scene, sensor, groups)
        self._check_kernel_size(scene, sensor, r0)
        connect = self.connects(sensor)
        # before the pools (the count's probe takes it too)
        lambertian_alone = self.direct_spp != 0 and self.lambertian_alone_for(scene, sensor)
        apart_emitter_samples = self.apart_emitter_samples_for(scene, sensor) if self.direct_spp != 0 else 0
        direct_spp = self.direct_spp_for(scene, sensor)
        stats = {"passes": 0, "kernel": self.kernel, "kernel_size": r0, "pool_spp": pool_spp, "pool_groups": groups,
                 "pools": [],
                 "direct_spp": direct_spp, "lambertian_alone": lambertian_alone,
                 "apart_emitter_samples": apart_emitter_samples,
                 "next_event_segments": next_event, "light_ratio": light_ratio,
                 **_pool_counters()}
        # pools of one lattice each where one sample per pixel does not fit (pool_spp is then 1)
        lattices = [film_lattice(target.film, groups, g) for g in range(groups)] if groups > 1 else [None]
        start = time.perf_counter()
        done, index, passes = 0, 0, 0
        while done < spp:
            if self.time_budget and done and time.perf_counter() - start >= self.time_budget:
                break  # the film averages exactly the finished pools (every lattice of a sample per pixel)
            n = min(pool_spp, spp - done)
            offset = self.spp_offset + done
            seed_n = pass_seed(seed, index)
            for group, pixels_of in enumerate(lattices):
                # the pool's position in the render, counting every lattice's pool
                position = offset * groups + group if groups > 1 else offset / pool_spp
                radius = kernel_size_at(r0, self.alpha, position)
                # the lattices of one sample per pixel: seeds from that sample's, the first its own, so that a
                # render split into calls of whole samples per pixel draws the same pools as one call
                pool_seed = pass_seed(seed_n, group)
                stats["pools"].append({"spp_offset": offset, "spp": n, "seed": pool_seed, "kernel_size": radius,
                                       **({"lattice": group} if groups > 1 else {})})
                wav = pool_wavelength_sample(seed if self.render_seed is None else self.render_seed,
                                             position) if mi.is_spectral else None
                self._render_pool(scene, sensor, target, n, pool_seed, radius, stats, wav, connect, direct_spp,
                                  check_sparse=passes == 0, next_event=next_event, pixels=pixels_of)
                passes += 1
            done += n
            index += 1
        stats["passes"] = passes
        stats["spp"] = done
        if done < spp:
            target.light_factor = spp / done  # light splats were weighed for all of spp (§4.11)
        self.last_stats = stats

    def sample_pool(self, scene: mi.Scene, sensor: mi.Sensor, spp: int, seed: int,
                    wavelength_sample: float | None = None, next_event: bool | None = None,
                    times: dict | None = None, pixels: mi.UInt32 | None = None):
        """Trace one pool's camera (and light) sub-paths and join their segments into one pool.

        Spectral variants: gathering joins segments of different walks, so every segment of the pool carries
        the same wavelengths. The camera rays all take one wavelength sample (``wavelength_sample``, by default
        that of a render's first pool of seed ``seed``: :func:`pool_wavelength_sample`),
        whose density their sensor weight holds; the light sub-paths take those wavelengths, their emission
        re-weighted as ``segment_bdpt``'s (``EmitterTerms.emitted_weight``, docs/maths.md §9.1, §10).

        ``next_event``: next-event segments join the pool (None: :meth:`next_event_for`).
        ``times``: receives the seconds of the camera walks (``camera``) and of the light walks (``light``), each
        up to the count of its records, which waits for it anyway.
        ``pixels``: the film samples whose camera samples the pool takes (None: all; a lattice of
        :meth:`pool_groups`).

        Returns ``(pool, camera sub-paths, number of light sub-paths)``; ``pool`` is None without any
        camera segment."""
        t0 = time.perf_counter()
        film_samples = film_sample_count(sensor.film())
        if next_event is None:
            next_event = self.next_event_for(scene, film_samples)
        n_cam = (film_samples if pixels is None else dr.width(pixels)) * spp
        sampler = prepare_sampler(sensor, seed, spp, n_cam)
        if wavelength_sample is None and mi.is_spectral:
            wavelength_sample = pool_wavelength_sample(seed)
        wav = wavelength_sample if mi.is_spectral else None
        paths = self.camera_sampler.sample(scene, sensor, sampler, spp, self.hide_emitters, wavelength_sample=wav,
                                           pixels=pixels)
        delta = has_delta_bsdf(scene)  # once per pool
        n_light = (max(1, int(round(self.light_ratio_for(scene, delta) * n_cam)))
                   if self.uses_light and scene.emitters() else 0)
        # room for every record the walks can make in their first loop (up to 8 vertices); deeper walks grow it
        depth = min(self.depth_limit, 8)
        buffer = RecordBuffer((n_cam + n_light) * depth)
        paths.record(SegmentRecorder(scene, CAMERA, n_cam, buffer))
        n_camera_segments = buffer.count()
        t1 = time.perf_counter()
        if n_camera_segments == 0:
            return None, paths, n_light

        reflecting = None
        if n_light:
            lsampler = prepare_sampler(sensor, seed ^ 0x5BD1E995, 1, n_light)
            light_sampler = self.light_sampler
            if self.emitted_light_sampler is not None and not has_mixed_bsdf(scene):
                light_sampler = self.emitted_light_sampler
            if mi.is_spectral:
                # the pool's wavelengths (every camera lane carries the same: take lane 0's)
                wavelengths = dr.gather(type(paths.wavelengths), paths.wavelengths, dr.zeros(mi.UInt32, n_light))
                lpaths = light_sampler.sample(scene, sensor, lsampler, n_light, wavelengths=wavelengths,
                                              emitted=EmitterTerms(scene).emitted_weight)
            else:
                lpaths = light_sampler.sample(scene, sensor, lsampler, n_light)
            light_rec = SegmentRecorder(scene, LIGHT, n_light, buffer, lpaths.emitter, lpaths.weight,
                                        (lpaths.ray, lpaths.sample2))
            lpaths.record(light_rec)
            reflecting = light_rec.emitter_surfaces()
        n_light_segments = buffer.count() - n_camera_segments
        if times is not None:
            times["camera"], times["light"] = t1 - t0, time.perf_counter() - t1
        n_next_event = 0
        if next_event:
            n_next_event = record_next_event(scene, buffer, n_camera_segments, seed,
                                             self.glossy_vertices == "private", every_delta=n_light == 0)
        pool = SegmentPool.build(scene, buffer, n_camera_segments, n_light_segments, reflecting, n_next_event)
        return pool, paths, n_light

    def _render_pool(self, scene, sensor, target: FilmTarget, spp: int, seed: int, radius: float,
                     stats: dict, wavelength_sample: float | None = None, connect: bool = False,
                     direct_spp: int = 0, check_sparse: bool = False, next_event: bool = False,
                     pixels: mi.UInt32 | None = None) -> None:
        """One pool into ``target``; ``connect``: caustic segments also go to the sensor (docs/maths.md §4.11);
        ``direct_spp``: camera samples per pool sample of the sharp direct light apart (§4.10);
        ``check_sparse``: measure how sparse its kernel domains are (a call's first pool, :meth:`_check_sparse`);
        ``next_event``: next-event segments join the pool (the render's :meth:`next_event_for`, §3.5);
        ``pixels``: the film samples it takes (None: all; a lattice of :meth:`pool_groups`)."""
        t0 = time.perf_counter()
        walks = {}
        pool, paths, n_light = self.sample_pool(scene, sensor, spp, seed, wavelength_sample, next_event, walks,
                                                pixels)
        if pool is None:
            return
        n_cam = dr.width(paths.position)  # the pool's camera samples: film samples (or the lattice's) x spp
        dr.sync_thread()
        t1 = time.perf_counter()

        estimator = MMISEstimator(scene, radius, n_light, self.kernel, seed,
                                  private_glossy=self.glossy_vertices == "private",
                                  light_delta_chains_only=self.light_delta_chains,
                                  next_event=next_event)
        system = estimator.build(pool)
        dr.sync_thread()
        t2 = time.perf_counter()

        emitted = pool.le
        if self.hide_emitters:
            emitted = dr.select((pool.kind == CAMERA) & (pool.index == 0), 0, emitted)
        apart = direct_spp > 0
        if apart:
            emitted = dr.select(pool.sharp, 0, emitted)  # the apart samples count it
        direct = (sharp_direct_light(scene, pool, system, self.depth_limit, seed, self.direct_light == "mis",
                                     self.direct_samples,
                                     delta_everywhere=not self.uses_light and not next_event,
                                     final_gather=self.final_gather, sharp_apart=apart)
                  if self.direct_light != "filtered" else None)
        dr.sync_thread()
        t_direct = time.perf_counter()
        # Pixel value: the sensor weight times the radiance of each camera sample's first segment.
        first = (pool.kind == CAMERA) & (pool.index == 0)
        first_edges = edge_subset(system, first)
        radiance = estimator.solve(pool, system, self.max_depth - 1, emitted, direct, first_edges)
        if connect and n_light:
            # the caustic segments gathered at the first vertices, partly connected to the sensor instead (§4.11)
            splat_weight = None
            if mi.is_spectral:
                splat_weight = dr.gather(mi.Spectrum, paths.sensor_weight, dr.zeros(mi.UInt32, 1))
            scale = dr.opaque(mi.Float, n_cam / target.spp)  # film samples x spp of the pool (§4.11)
            radiance = split_first_gather(scene, sensor, estimator, pool, system, radiance, emitted, direct, n_cam,
                                          target.light_block, scale, seed, self.light_tracing_balance,
                                          splat_weight, self.first_survival(), first_edges)
        value = dr.zeros(mi.Spectrum, n_cam)
        dr.scatter(value, radiance, pool.pixel, first)
        alpha = dr.zeros(mi.Float, n_cam)
        dr.scatter(alpha, dr.select(pool.surf.valid, 1.0, 0.0), pool.pixel, first)
        dr.eval(value, alpha)
        target.splat_camera(paths.position, paths.sensor_weight * value, paths.wavelengths, alpha)
        dr.eval(target.camera_block.tensor())
        dr.sync_thread()
        t3 = time.perf_counter()
        if apart:
            self._render_apart(scene, sensor, target, spp * direct_spp, seed, pixels=pixels)
            dr.sync_thread()
        t4 = time.perf_counter()
        if check_sparse:
            self._check_sparse(system, radius, spp, stats, lattice=pixels is not None)
        stats["segments"] += pool.size
        stats["camera_segments"] += pool.camera_count
        stats["light_segments"] += pool.light_count
        stats["light_paths"] += n_light
        stats["time_camera_walks"] += walks["camera"]
        stats["time_light_walks"] += walks["light"]
        stats["edges"] += system.edge_count
        stats["lumped"] += system.lumped_count
        stats["time_trace"] += t1 - t0
        stats["time_system"] += t2 - t1
        stats["time_solve"] += t3 - t2
        stats["time_rows"] += t_direct - t2
        stats["time_apart"] += t4 - t3

    def _check_kernel_size(self, scene: mi.Scene, sensor: mi.Sensor, r0: float) -> None:
        """Warn, once per integrator, where the first kernel is wider than the scene's bounding sphere: with a
        film of a few pixels (mi.cornell_box() at 1x1: segment_pf 0.59x, segment_bdf 0.55x of path with hidden
        emitters, and 1.24x / 1.04x with pools of 1024 samples; at 8x8, below the bound, the means are within a
        few percent; docs/maths.md §5.3)."""
        box = scene.bbox()
        if not box.valid() or self._warned_kernel:
            return
        diameter = 2 * box.bounding_sphere().radius
        if r0 > diameter:
            self._warned_kernel = True
            size = "x".join(str(v) for v in sensor.film().crop_size())
            source = (f"kernel_size {r0:.3g}" if self.kernel_size else
                      f"a kernel of size {r0:.3g} (derived from the pixel footprints of a {size} film)")
            warnings.warn(
                f"{self.plugin_name}: {source} is wider than the whole scene (bounding sphere diameter "
                f"{diameter:.3g}): each pool is then one blur of the scene, biased far beyond a kernel's blur "
                "(a 1x1 Cornell box: 0.55-1.24x of path). Render more pixels (on the benchmark scenes 8x8 and up "
                "keep the derived kernel inside the scene) or set a smaller kernel_size.", KernelSizeWarning,
                stacklevel=2)

    def _check_sparse(self, system, radius: float, spp: int, stats: dict, lattice: bool = False) -> None:
        """On a call's first pool: the share of its queries whose kernel domain is sparse, into ``stats``, and in
        ``segment_bdf`` (camera and light techniques in one pool) a warning when most are, once per integrator."""
        share = system.sparse_share()
        stats["sparse_queries"] = share
        if self.uses_camera and self.uses_light and share > SPARSE_WARN_SHARE and not self._warned_sparse:
            self._warned_sparse = True
            size = "one film lattice" if lattice else f"{spp} spp"
            more = ("a larger memory_budget (fewer, fuller film lattices, docs/maths.md §5.7)" if lattice
                    else "more spp_per_pass")
            warnings.warn(
                f"{self.plugin_name}: {share:.0%} of the queries of a pool ({size}, {self.kernel} kernel of size "
                f"{radius:.3g}) gather from a kernel domain that holds about two walk vertices; pools this sparse "
                f"come out too bright (docs/maths.md §8.1, item 4). A larger kernel_size (0 derives it from the "
                f"scene) or {more} avoids it.", SparsePoolWarning, stacklevel=2)

    def _render_apart(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, spp: int, seed: int,
                      lambertian_alone: bool | None = None, emitter_samples: int | None = None,
                      stratified: bool = True, pixels: mi.UInt32 | None = None) -> None:
        """The sharp direct light of ``spp`` camera samples per pixel of its own (docs/maths.md §4.10);
        ``lambertian_alone``: None takes :meth:`lambertian_alone_for`; ``emitter_samples`` (per vertex): None takes
        :meth:`apart_emitter_samples_for`; ``stratified``: a vertex's emitter samples stratified; ``pixels``: the
        film samples they take (None: all)."""
        if lambertian_alone is None:
            lambertian_alone = self.lambertian_alone_for(scene, sensor)
        if emitter_samples is None:
            emitter_samples = self.apart_emitter_samples_for(scene, sensor)
        count = film_sample_count(target.film) if pixels is None else dr.width(pixels)
        # wavefronts of at most ~2M samples: the walk's state is a few hundred bytes per lane
        chunk = max(1, min(spp, _APART_LANES // max(count, 1)))
        done, index = 0, 0
        while done < spp:
            n = min(chunk, spp - done)
            sampler = prepare_sampler(sensor, pass_seed(seed ^ 0x2F6B3A91, index), n, count * n)
            ray, weight, pos = sample_camera_rays(sensor, sampler, n, pixels=pixels)
            value = sharp_chain_light(scene, sampler, ray, self.depth_limit, self.hide_emitters, lambertian_alone,
                                      emitter_samples, stratified)
            target.splat_apart(pos, weight * value, ray.wavelengths)
            dr.eval(target.apart_block.tensor())
            done, index = done + n, index + 1

    def to_string(self) -> str:
        light = f"light_ratio={'derived' if self.light_ratio is None else self.light_ratio}, " if self.uses_light \
            else ""
        scale = "derived" if self.kernel_scale is None else self.kernel_scale
        split = self.apart_emitter_samples
        next_event = "derived" if self.next_event_segments is None else self.next_event_segments
        return (f"{type(self).__name__}[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"kernel={self.kernel}, direct_light={self.direct_light}, direct_samples={self.direct_samples}, "
                f"direct_spp={'derived' if self.direct_spp is None else self.direct_spp}, "
                f"apart_emitter_samples={'derived' if split is None else split}, "
                f"light_tracing={self.light_tracing}, "
                f"next_event_segments={next_event}, "
                f"glossy_vertices={self.glossy_vertices}, final_gather={self.final_gather}, "
                f"kernel_size={self.kernel_size or f'{scale} x pixel footprint'}, "
                f"alpha={self.alpha}, {light}memory_budget={self.memory_budget} MiB]")
