"""What every segmitsuba integrator shares: property parsing, scene checks and film/sampler set-up.

This module is re-imported on every variant change (see ``segmitsuba.registry``), because
``SegmentIntegrator`` derives from the current variant's ``mi.SamplingIntegrator``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..film import FilmTarget
from ..samplers.emission import emission_of, emitter_class, overlapping_texture_charts, repair_emission_bounds


class PropertyReader:
    """Reads and validates plugin properties with clear messages naming the plugin and the property."""

    def __init__(self, plugin: str, props: mi.Properties):
        self.plugin = plugin
        self.props = props

    def _fail(self, name: str, msg: str) -> None:
        raise ValueError(f"{self.plugin}: property '{name}' {msg}")

    def integer(self, name: str, default: int, minimum: int | None = None, allow: tuple[int, ...] = (),
                maximum: int | None = None) -> int:
        if name not in self.props:
            return default
        v = self.props[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or float(v) != int(v):
            self._fail(name, f"must be an integer, got {v!r}")
        v = int(v)
        if v not in allow and minimum is not None and v < minimum:
            extra = f" (or {', '.join(map(str, allow))})" if allow else ""
            self._fail(name, f"must be >= {minimum}{extra}, got {v}")
        if maximum is not None and v > maximum:
            self._fail(name, f"must be <= {maximum}, got {v}")
        return v

    def real(self, name: str, default: float, minimum: float | None = None, maximum: float | None = None,
             exclusive_min: bool = False) -> float:
        if name not in self.props:
            return default
        v = self.props[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self._fail(name, f"must be a number, got {v!r}")
        v = float(v)
        if v != v or v in (float("inf"), float("-inf")):
            self._fail(name, f"must be finite, got {v}")
        if minimum is not None and (v < minimum or (exclusive_min and v == minimum)):
            self._fail(name, f"must be {'>' if exclusive_min else '>='} {minimum}, got {v}")
        if maximum is not None and v > maximum:
            self._fail(name, f"must be <= {maximum}, got {v}")
        return v

    def boolean(self, name: str, default: bool) -> bool:
        if name not in self.props:
            return default
        v = self.props[name]
        if not isinstance(v, bool):
            self._fail(name, f"must be a boolean, got {v!r}")
        return v

    def choice(self, name: str, default: str, options: tuple[str, ...]) -> str:
        if name not in self.props:
            return default
        v = self.props[name]
        if v not in options:
            self._fail(name, f"must be one of {', '.join(options)}, got {v!r}")
        return v


#: emitter plugins (class names) whose sampling Mitsuba does not keep consistent with their radiance, and why: an
#: integrator that weighs their samples against other techniques, or traces light from them, renders them wrong
INCONSISTENT_EMITTERS = {
    "SunskyEmitter": "Mitsuba's sunsky does not emit light sub-paths consistently with its radiance (its own "
                     "ptracer renders a test scene at 0.2x path; the sky alone 0.28x, the sun alone 0.18x; mitsuba3 "
                     "pull request #1721 fixes one inconsistency of its sun), and segment_bdpt came out at 0.42x, "
                     "segment_mvf at 1.26x",
}


def check_scene(plugin: str, scene: mi.Scene, sensor: mi.Sensor, light_paths: bool = False,
                consistent_emitters: bool = True) -> None:
    """Refuse what the segment formulation does not cover yet (participating media), naming it.

    With ``light_paths``, also refuse emitters that cannot emit light sub-paths: those whose radiance Mitsuba
    cannot sample (procedural textures such as ``checkerboard``; its ``ptracer`` fails there with an obscure
    message), unless they are area lights, which :mod:`segmitsuba.samplers.emission` emits from itself. With
    ``consistent_emitters``, refuse the emitters of :data:`INCONSISTENT_EMITTERS`. Environment and
    directional emitters get a bounding sphere that holds the scene where Mitsuba's box misses a merged mesh
    (:func:`~segmitsuba.samplers.emission.repair_emission_bounds`).
    """
    media = [s.id() or type(s).__name__ for s in scene.shapes()
             if s.interior_medium() is not None or s.exterior_medium() is not None]
    if sensor.get_medium() is not None:
        media.append(f"sensor '{sensor.id()}'")
    if media:
        raise RuntimeError(
            f"{plugin}: participating media are not supported yet (found on: {', '.join(media)}). "
            "Render this scene with Mitsuba's 'volpath', or remove the media."
        )
    if consistent_emitters:
        for emitter in scene.emitters():
            why = INCONSISTENT_EMITTERS.get(emitter_class(emitter))
            if why is not None:
                raise RuntimeError(
                    f"{plugin}: emitter '{emitter.id()}' is not supported: {why}. Render it with segment_pt (or "
                    "Mitsuba's path), or replace it by an envmap of the sky.")
            cover = overlapping_texture_charts(emitter)
            if cover is not None:
                charts = ("has no texture coordinates" if cover == float("inf") else
                          f"has texture coordinates that cover the unit square {cover:.3g} times")
                raise RuntimeError(
                    f"{plugin}: emitter '{emitter.id()}' is not supported: its radiance varies over mesh "
                    f"'{emitter.get_shape().id()}', which {charts}, and Mitsuba samples such a light's positions "
                    "from one chart only, so its emitter samples no longer match its radiance (a bitmap on a "
                    "cube: path 0.80x and ptracer 0.19x of BSDF sampling alone). Give the mesh texture "
                    "coordinates that do not overlap (or the light a uniform radiance), or render it with "
                    "segment_pt, which renders what Mitsuba's path renders.")
    repair_emission_bounds(scene)
    if not light_paths:
        return
    for emitter in scene.emitters():
        if emission_of(emitter) is None:
            raise RuntimeError(
                f"{plugin}: emitter '{emitter.id()}' cannot emit light sub-paths: Mitsuba can neither sample "
                f"nor evaluate its radiance in variant {mi.variant()} (a 'raw' bitmap in a spectral variant?). "
                "Use an RGB variant, a texture that is not raw, or a camera-only integrator (segment_pt)."
            )


class SegmentIntegrator(mi.SamplingIntegrator):
    """Base of segmitsuba's integrators: Mitsuba's path-depth properties, validated, and the shared ``render``.

    ``render`` does what every plugin needs once (the sensor, the scene checks, the film and its blocks, the
    sample count, developing) and calls :meth:`render_samples`, which each plugin implements with what it
    estimates, as Mitsuba's ``ADIntegrator.render`` / ``sample`` split does.
    """

    plugin_name = "segment"
    default_max_depth = 6
    #: light sub-paths are traced: the emitters must be able to sample their radiance (see check_scene)
    uses_light_paths = False
    #: its estimate relies on the emitters' sampling agreeing with their radiance (see INCONSISTENT_EMITTERS);
    #: segment_pt only does what Mitsuba's path does with them
    needs_consistent_emitters = True
    #: the light-tracing image is divided by the film's splat coverage (see film.FilmTarget)
    normalize_light = False

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        read = PropertyReader(self.plugin_name, props)
        #: longest path, in segments between sensor and emitter (Mitsuba's definition; -1: unbounded)
        self.max_depth = read.integer("max_depth", self.default_max_depth, minimum=0, allow=(-1,))
        self.rr_depth = read.integer("rr_depth", 5, minimum=1)
        self.hide_emitters = read.boolean("hide_emitters", False)

    @property
    def depth_limit(self) -> int:
        return 0xFFFFFFFF if self.max_depth == -1 else self.max_depth

    def render(self, scene: mi.Scene, sensor: int | mi.Sensor = 0, seed: int | mi.UInt32 = 0, spp: int = 0,
               develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        if isinstance(sensor, int):
            if not 0 <= sensor < len(scene.sensors()):
                raise ValueError(f"{self.plugin_name}: sensor index {sensor} is out of range: the scene has "
                                 f"{len(scene.sensors())} sensor(s)")
            sensor = scene.sensors()[sensor]
        if spp < 0:
            raise ValueError(f"{self.plugin_name}: spp must be >= 0 (0: the sensor's sample count), got {spp}")
        if dr.is_array_v(seed):  # mi.render also takes a UInt32 seed (and Mitsuba's aov integrator passes one)
            if dr.width(seed) != 1:
                raise ValueError(f"{self.plugin_name}: one seed per render, got an array of {dr.width(seed)}")
            seed = int(seed[0])
        check_scene(self.plugin_name, scene, sensor, light_paths=self.uses_light_paths,
                    consistent_emitters=self.needs_consistent_emitters)
        spp = spp or sensor.sampler().sample_count()
        target = FilmTarget(sensor.film(), spp, self.normalize_light)
        with dr.suspend_grad():
            self.render_samples(scene, sensor, target, seed, spp)
            return target.develop(develop, evaluate)

    def render_samples(self, scene: mi.Scene, sensor: mi.Sensor, target: FilmTarget, seed: int, spp: int) -> None:
        """Trace ``spp`` samples per pixel with ``seed`` and put them into ``target``'s blocks."""
        raise NotImplementedError

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f, medium: mi.Medium = None,
               active: mi.Bool = True, *args, **kwargs):
        """Mitsuba's per-ray entry point, which integrators that nest another (``aov``, ``moment``) call. Ours
        estimate whole wavefronts (a pool, a light-tracing splat) through :meth:`render` and cannot answer one
        ray at a time: refuse by name instead of Mitsuba's 'tried to call a pure virtual function'."""
        raise RuntimeError(
            f"{self.plugin_name}: renders whole images through mi.render and cannot estimate one ray at a time, "
            "which integrators that nest another (aov, moment) ask for. Render it directly; for AOVs, render "
            "Mitsuba's aov integrator on its own alongside it.")

    def aov_names(self) -> list[str]:
        return []

    def to_string(self) -> str:
        return (f"{type(self).__name__}[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"hide_emitters={self.hide_emitters}]")
