"""segment_bdpt is unbiased: z-tests against Mitsuba's path (and ptracer where path misses paths).

Same statistics as tests/test_sequential_vs_mitsuba.py: per-seed image and 3x3 tile means, Student-t
converted to normal z, |z| < 4. Seeds of the two renderers are disjoint. Spectral variants, thin-lens and
orthographic sensors and develop=False are in tests/test_sensors_spectral.py.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES
from stats import compare, render_seeds

# textured.xml: its checkerboard emitter emits through segmitsuba.samplers.emission (Mitsuba cannot sample it);
# delta_caustic_point.xml: path cannot reach point light -> glass -> diffuse (tested against ptracer);
# medium.xml: participating media are refused.
SKIP = {"delta_caustic_point.xml", "medium.xml"}
SCENE_FILES = sorted(p.name for p in SCENES.glob("*.xml") if p.name not in SKIP)
K, SPP, RES = 8, 16, 32


def load(name: str, **defines) -> mi.Scene:
    return mi.load_file(str(SCENES / name), res=RES, **defines)


def bdpt(**props) -> mi.Integrator:
    return mi.load_dict({"type": "segment_bdpt", **props})


@pytest.mark.parametrize("scene_file", SCENE_FILES)
def test_agrees_with_path(scene_file):
    scene = load(scene_file)
    a = render_seeds(scene, bdpt(max_depth=6), SPP, range(K))
    b = render_seeds(scene, mi.load_dict({"type": "path", "max_depth": 6}), SPP, range(1000, 1000 + K))
    assert np.isfinite(a).all()
    result = compare(a, b, tiles=3)
    print(scene_file, result)
    assert result.mean_b > 0
    assert result.max_abs < 4, str(result)


@pytest.mark.parametrize("max_depth", [2, 3])
def test_short_paths_agree_with_path(max_depth):
    """Depth limits cut every technique at the same path length (glossy scene: every technique matters)."""
    scene = load("glossy_occluded.xml")
    a = render_seeds(scene, bdpt(max_depth=max_depth), SPP, range(K))
    b = render_seeds(scene, mi.load_dict({"type": "path", "max_depth": max_depth}), SPP, range(1000, 1000 + K))
    result = compare(a, b, tiles=3)
    assert result.max_abs < 4, str(result)


def test_delta_caustic_agrees_with_ptracer_and_finds_what_path_misses():
    """A point light seen through glass on a diffuse floor: only light tracing and bridges from light
    vertices behind the glass reach it. segment_bdpt agrees with ptracer on the whole image, and is
    significantly brighter than path where the caustic lands (path has no technique for those paths)."""
    scene = load("delta_caustic_point.xml")
    a = render_seeds(scene, bdpt(max_depth=6), SPP, range(K))
    b = render_seeds(scene, mi.load_dict({"type": "ptracer", "max_depth": 6}), SPP, range(1000, 1000 + K))
    result = compare(a, b, tiles=3)
    assert result.max_abs < 4, str(result)
    c = render_seeds(scene, mi.load_dict({"type": "path", "max_depth": 6}), SPP, range(2000, 2000 + K))
    missing = compare(a, c, tiles=3)
    assert np.max(missing.z_tiles) > 4, f"the caustic should be missing from path: {missing}"


def test_film_features_crop_alpha_gaussian_and_hidden_emitters():
    """Crop window, alpha, a gaussian filter (light-tracing splats are normalized by the filter coverage at
    the borders, as camera samples are) and hide_emitters, against path."""
    d = mi.cornell_box()
    d["sensor"]["film"] = {"type": "hdrfilm", "width": 48, "height": 40, "pixel_format": "rgba",
                           "crop_offset_x": 8, "crop_offset_y": 4, "crop_width": 32, "crop_height": 24,
                           "rfilter": {"type": "gaussian"}}
    scene = mi.load_dict(d)
    for props in ({}, {"hide_emitters": True}):
        a = render_seeds(scene, bdpt(**props), SPP, range(K))
        b = render_seeds(scene, mi.load_dict({"type": "path", **props}), SPP, range(1000, 1000 + K))
        assert a.shape == b.shape == (K, 24, 32, 4)
        result = compare(a, b, tiles=4)
        assert result.max_abs < 4, f"{props}: {result}"
        alpha = compare(np.repeat(a[..., 3:4], 3, -1), np.repeat(b[..., 3:4], 3, -1), tiles=3)
        assert alpha.max_abs < 4, f"alpha {props}: {alpha}"


def test_mono_variant_renders():
    mi.set_variant("llvm_ad_mono")
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 16
    img = np.array(mi.render(mi.load_dict(d), integrator=bdpt(), spp=4))
    assert np.isfinite(img).all() and img.mean() > 0.01


def test_refused_scene_features():
    with pytest.raises(Exception) as info:
        mi.render(load("medium.xml"), integrator=bdpt(), spp=1)
    assert "participating media" in repr(info.value) or "participating media" in str(info.value.__cause__)
    del info
    import gc

    gc.collect()


def test_area_lights_mitsuba_cannot_sample_emit_as_mitsuba_would(monkeypatch):
    """``samplers.emission.sample_emitter_ray`` emits from area lights whose radiance Mitsuba cannot sample (a
    checkerboard) as ``AreaLight.sample_ray`` would: forced onto textured_bitmap's light, whose radiance Mitsuba
    can sample, it gives Mitsuba's rays and weights; textured.xml's checkerboard light then emits (its images
    are held against ``path`` by the z-tests above)."""
    from segmitsuba.samplers import emission

    scene = load("textured_bitmap.xml")
    n = 4096
    rng = np.random.default_rng(3)
    args = (mi.Float(rng.random(n)), mi.Float(rng.random(n)), mi.Point2f(rng.random((2, n))),
            mi.Point2f(rng.random((2, n))), dr.full(mi.Bool, True, n))
    ray_m, weight_m, _ = scene.sample_emitter_ray(*args)
    own = emission.emission_of
    monkeypatch.setattr(emission, "emission_of", lambda e: emission.EVALUATED if e.get_shape() is not None else own(e))
    ray, weight, emitter = emission.sample_emitter_ray(scene, *args)
    assert np.allclose(np.array(ray.o), np.array(ray_m.o), atol=1e-6)
    assert np.allclose(np.array(ray.d), np.array(ray_m.d), atol=1e-6)
    assert np.allclose(np.array(weight), np.array(weight_m), rtol=1e-5)
    assert np.array(weight).max() > 0
    monkeypatch.undo()

    checker = load("textured.xml")
    assert emission.emission_of(checker.emitters()[0]) == emission.EVALUATED
    ray, weight, emitter = emission.sample_emitter_ray(checker, *args)
    w = np.array(weight)
    # the checkerboard's two radiances, times pi times the light's area (1.2 x 1.2)
    assert np.isfinite(w).all() and len(np.unique(np.round(w[0], 3))) == 2
    assert np.allclose(np.unique(np.round(w[0], 3)), np.array([0.3, 5.0]) * np.pi * 1.44, rtol=1e-3)


def test_bad_properties():
    for props, message in (({"max_depth": -2}, "max_depth"), ({"rr_depth": 0}, "rr_depth"),
                           ({"hide_emitters": 1}, "hide_emitters"), ({"kernel": "radius"}, "kernel")):
        with pytest.raises(Exception, match=message):
            mi.load_dict({"type": "segment_bdpt", **props})


def test_emitterless_scene_is_black():
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {"type": "hdrfilm",
                                                                                      "width": 8, "height": 8}},
                          "shape": {"type": "sphere"}})
    img = np.array(mi.render(scene, integrator=bdpt(), spp=2))
    assert np.isfinite(img).all() and img.max() == 0
