"""Emitted rays for every emitter, including area lights whose radiance Mitsuba cannot sample spectrally.

``Scene.sample_emitter_ray`` asks each emitter for a ray, and an area light's ``sample_ray`` draws the emitted
wavelengths from its radiance texture (``Texture.sample_spectrum``). Procedural textures such as
``checkerboard`` do not implement that, so Mitsuba's own ``ptracer`` fails on such a light, although nothing
else about emitting from it is hard: the position is the shape's (uniform in area, as for any area light) and
the direction cosine-distributed, neither depends on the texture. Here those lights emit as ``AreaLight``
does, with the wavelengths drawn as an RGB-upsampled texture draws them (``sample_rgb_spectrum``) and the
texture evaluated there: the same rays and weights in expectation, and the same densities for the MMIS
denominators and ``segment_bdpt``'s weights (docs/maths.md §3.3). Scenes whose emitters all sample their
radiance take ``Scene.sample_emitter_ray`` itself.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def _traces(call) -> bool:
    """Whether ``call(si)`` evaluates at a one-lane surface point seen from its front side; Mitsuba raises
    while tracing what a plugin does not implement."""
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(0, 0, 1)
    try:
        dr.eval(call(si))
    except RuntimeError:
        return False
    return True


#: how an emitter emits light sub-paths (:func:`emission_of`)
SAMPLED, EVALUATED = "sampled", "evaluated"


def emitter_class(emitter: mi.Emitter) -> str:
    """The C++ class of an emitter plugin (``PointLight``, ``SunskyEmitter``, ...): Python sees every emitter as
    ``Emitter``, its string form names the class."""
    return str(emitter).split("[", 1)[0].strip()


def emission_of(emitter: mi.Emitter) -> str | None:
    """:data:`SAMPLED`: Mitsuba samples its radiance (``sample_wavelengths``, which its ``sample_ray`` needs).
    :data:`EVALUATED`: an area light (a shape, emitting by cosine from its front side) whose radiance Mitsuba
    cannot sample but can evaluate; :func:`sample_emitter_ray` emits from it on its own. None: neither (a ``raw``
    bitmap in a spectral variant cannot even be evaluated)."""
    if _traces(lambda si: emitter.sample_wavelengths(si, mi.Float(0.5), True)):
        return SAMPLED
    if (emitter.get_shape() is not None and not mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
            and _traces(lambda si: emitter.eval(si, True))):
        return EVALUATED
    return None


def _texture_wavelengths(emitter: mi.Emitter, si: mi.SurfaceInteraction3f, sample: mi.Float,
                         active: mi.Bool) -> tuple:
    """For an emitter Mitsuba cannot sample (:data:`EVALUATED`): the wavelengths of an
    RGB-upsampled spectrum (stratified from ``sample`` as Mitsuba's ``sample_shifted``), and the radiance at
    ``si`` there over their density; in RGB the radiance. As ``sample_wavelengths``, it ignores ``si.wi``."""
    si = mi.SurfaceInteraction3f(si)
    si.wi = mi.Vector3f(0, 0, 1)  # eval counts the front side only: the caller's direction is not asked here
    weight = mi.Float(1.0)
    if mi.is_spectral:
        n = dr.size_v(mi.Spectrum)
        shifted = type(si.wavelengths)([(sample + i / n) - dr.floor(sample + i / n) for i in range(n)])
        si.wavelengths, weight = mi.sample_rgb_spectrum(shifted)
    return si.wavelengths, dr.select(active, mi.unpolarized_spectrum(emitter.eval(si, active)) * weight, 0)


def sample_wavelengths(scene: mi.Scene, index: mi.UInt32, si: mi.SurfaceInteraction3f, sample: mi.Float,
                       active: mi.Bool) -> tuple:
    """``sample_wavelengths`` of the emitters ``index`` (of ``scene.emitters()``) at ``si``: Mitsuba's, or for
    emitters that cannot sample their radiance, :func:`_texture_wavelengths`."""
    emitters = scene.emitters()
    unsampled = [emission_of(e) != SAMPLED for e in emitters]
    if not any(unsampled):
        try:
            emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, active)
            return emitter.sample_wavelengths(si, sample, active)
        except RuntimeError:
            pass  # a virtual call traces every live emitter, also those of other scenes that cannot sample
    wavelengths = type(si.wavelengths)(si.wavelengths)
    weight = dr.zeros(mi.UnpolarizedSpectrum, dr.width(sample))
    for i, (e, u) in enumerate(zip(emitters, unsampled, strict=True)):
        mine = active & (index == i)
        w, v = _texture_wavelengths(e, si, sample, mine) if u else e.sample_wavelengths(si, sample, mine)
        if mi.is_spectral:  # RGB variants carry no wavelengths
            wavelengths[mine] = w
        weight[mine] = v
    return wavelengths, weight


def _area_ray(emitter: mi.Emitter, time: mi.Float, sample1: mi.Float, sample2: mi.Point2f, sample3: mi.Point2f,
              active: mi.Bool) -> tuple[mi.Ray3f, mi.Spectrum]:
    """``AreaLight.sample_ray`` with :func:`_texture_wavelengths`: a position uniform in area, a cosine-weighted
    direction, weight ``radiance * pi / pdf(position)``."""
    ps, pos_weight = emitter.sample_position(time, sample2, active)
    local = mi.warp.square_to_cosine_hemisphere(sample3)
    si = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Interaction3f, dr.width(time)).wavelengths)
    si.time = time
    si.wavelengths, wav_weight = _texture_wavelengths(emitter, si, sample1, active)
    return si.spawn_ray(si.to_world(local)), mi.Spectrum(wav_weight) * pos_weight * dr.pi


def sample_emitter_ray(scene: mi.Scene, time: mi.Float, sample1: mi.Float, sample2: mi.Point2f,
                       sample3: mi.Point2f, active: mi.Bool) -> tuple[mi.Ray3f, mi.Spectrum, mi.EmitterPtr]:
    """``scene.sample_emitter_ray``, also for area lights whose radiance Mitsuba cannot sample
    (:data:`EVALUATED`): then the emitter is selected as the scene selects it, with the reused
    ``sample1``, and each emitter emits in turn (a few masked passes over the lanes, paid only by such scenes).
    Other emitters that cannot sample their radiance raise an error naming them."""
    emitters = scene.emitters()
    kinds = [emission_of(e) for e in emitters]
    if all(k == SAMPLED for k in kinds):
        try:
            return scene.sample_emitter_ray(time, sample1, sample2, sample3, active)
        except RuntimeError:
            # Dr.Jit traces a virtual call for every live emitter, those of other scenes included: one that
            # cannot sample its radiance breaks it here too, and the direct calls below do not trace it
            pass
    for e, k in zip(emitters, kinds, strict=True):
        if k is None:
            raise RuntimeError(f"emitter '{e.id()}' cannot emit light sub-paths: its radiance cannot be "
                               "sampled in Mitsuba")
    n = dr.width(sample1)
    if len(emitters) == 1:
        index, selection, reused = dr.zeros(mi.UInt32, n), mi.Float(1.0), mi.Float(sample1)
    else:
        index, selection, reused = scene.sample_emitter(sample1, active)
    ray = dr.zeros(mi.Ray3f, n)
    weight = dr.zeros(mi.Spectrum, n)
    for i, (e, k) in enumerate(zip(emitters, kinds, strict=True)):
        mine = active & (index == i)
        r, w = (_area_ray(e, time, reused, sample2, sample3, mine) if k == EVALUATED
                else e.sample_ray(time, reused, sample2, sample3, mine))
        ray[mine] = r
        weight[mine] = w
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, active)
    return ray, weight * selection, emitter


def bounded_emitters(scene: mi.Scene) -> list[mi.Emitter]:
    """The emitters that emit across the scene's bounding sphere (environments, directional)."""
    return [e for e in scene.emitters() if mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)
            or mi.has_flag(e.flags(), mi.EmitterFlags.DeltaDirection)]


def _vertex_box(mesh: mi.Mesh) -> mi.ScalarBoundingBox3f | None:
    p = mesh.vertex_positions_buffer()
    if dr.width(p) == 0:
        return None
    v = dr.unravel(mi.Point3f, p)
    return mi.ScalarBoundingBox3f(mi.ScalarPoint3f([float(dr.min(c)[0]) for c in (v.x, v.y, v.z)]),
                                  mi.ScalarPoint3f([float(dr.max(c)[0]) for c in (v.x, v.y, v.z)]))


def _holds(box: mi.ScalarBoundingBox3f, inner: mi.ScalarBoundingBox3f) -> bool:
    if not inner.valid():
        return True
    if not box.valid():
        return False
    slack = 1e-4 * max(1.0, max(inner.extents()))
    return all(inner.min[i] >= box.min[i] - slack and inner.max[i] <= box.max[i] + slack for i in range(3))


def emission_bounds(scene: mi.Scene) -> mi.ScalarBoundingBox3f:
    """The box whose bounding sphere environment and directional emitters emit across: the scene's, or, where
    it does not hold the shapes' own boxes, their union (what :func:`repair_emission_bounds` gives the emitters).
    """
    box = scene.bbox()
    if not bounded_emitters(scene):
        return box  # nothing emits across it: no need to look at every shape
    union = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        union.expand(shape.bbox())
    return box if _holds(box, union) else union


def repair_emission_bounds(scene: mi.Scene) -> None:
    """Mitsuba merges shapes that share a BSDF into one mesh and may give it the bounding box of one of its parts
    (or none), and so the scene too; environment and directional emitters then emit across a sphere that misses
    the scene (its ``ptracer`` renders such a scene black). Recomputes the boxes of such meshes (their own
    geometry untouched) and, where the scene's box does not hold them, gives those emitters the sphere of the
    shapes' union (``set_scene`` of a scene of one box), which :func:`emission_bounds` reports to the densities."""
    emitters = bounded_emitters(scene)
    if not emitters:
        return
    for shape in scene.shapes():
        if isinstance(shape, mi.Mesh):
            box = _vertex_box(shape)
            if box is not None and not _holds(shape.bbox(), box):
                shape.recompute_bbox()
    box = emission_bounds(scene)
    if box.valid() and not _holds(scene.bbox(), box):
        t = mi.ScalarTransform4f().translate(box.center()).scale(mi.ScalarVector3f(
            [max(0.5 * x, 1e-6) for x in box.extents()]))
        holder = mi.load_dict({"type": "scene", "box": {"type": "cube", "to_world": t}})
        for e in emitters:
            e.set_scene(holder)


def overlapping_texture_charts(emitter: mi.Emitter) -> float | None:
    """For an area light of spatially varying radiance on a mesh: how many times its triangles' texture
    coordinates cover the unit square (infinity without texture coordinates) where that is more than once, else
    None. Mitsuba samples such a light's positions in proportion to its texture through the inverse of the
    mesh's parameterization, which reaches one chart where several overlap (a ``cube``'s six faces all map to
    the unit square: every sample lands on one face), so its emitter sampling no longer matches its radiance."""
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite) or not mi.has_flag(
            emitter.flags(), mi.EmitterFlags.SpatiallyVarying):
        return None
    shape = emitter.get_shape()
    if not isinstance(shape, mi.Mesh):
        return None
    if not shape.has_vertex_texcoords():
        return float("inf")
    f = dr.unravel(mi.Vector3u, shape.faces_buffer())
    uv = dr.unravel(mi.Point2f, shape.vertex_texcoords_buffer())
    a, b, c = (dr.gather(mi.Point2f, uv, f[i]) for i in range(3))
    cover = float(dr.sum(0.5 * dr.abs((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y)))[0])
    return cover if cover > 1.01 else None
