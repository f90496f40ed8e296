"""Light tracing beyond the pinhole and RGB: thin-lens and orthographic sensors, spectral variants, and
``develop=False`` for the integrators that splat light-tracing samples.

Same statistics as tests/test_bdpt.py (per-seed image and 3x3 tile means, Student-t converted to normal z,
|z| < 4, disjoint seeds), at 16x16 to keep the spectral kernels cheap, with Mitsuba's reference at 4x the
samples. Spectral renders are also compared channel by channel. Scenes are the files in scenes/, some with
their sensor replaced (:func:`with_sensor`).
"""

from __future__ import annotations

import functools
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES, error_chain
from stats import compare, render_seeds

K, SPP, RES = 8, 16, 16


def with_sensor(name: str, kind: str, res: int = RES) -> mi.Scene:
    """Scene file ``name`` with its ``perspective`` sensor replaced by a ``thinlens`` (aperture 0.3, focused
    at 3) or an ``orthographic`` one (the same view axis, 2.4 units across)."""
    xml = (SCENES / name).read_text()
    if kind == "thinlens":
        xml = xml.replace('<sensor type="perspective">', '<sensor type="thinlens">'
                          '<float name="aperture_radius" value="0.3"/><float name="focus_distance" value="3"/>', 1)
    elif kind == "orthographic":
        xml = xml.replace('<sensor type="perspective">', '<sensor type="orthographic">', 1)
        xml = re.sub(r'<float name="fov"[^>]*/>', "", xml, count=1)
        xml = xml.replace("<lookat", '<scale x="1.2" y="1.2"/><lookat', 1)
    else:
        raise ValueError(kind)
    assert f'type="{kind}"' in xml
    return mi.load_string(xml, res=res)


def load(name: str, res: int = RES) -> mi.Scene:
    return mi.load_file(str(SCENES / name), res=res)


def agree(scene: mi.Scene, ours: str, theirs: str, spp: int = SPP, k: int = K, channels: bool = False):
    """z-test of ``ours`` against Mitsuba's ``theirs``, which is cheap and renders 4x the samples (less of
    the difference's noise is the reference's)."""
    a = render_seeds(scene, mi.load_dict({"type": ours, "max_depth": 6}), spp, range(k))
    b = render_seeds(scene, mi.load_dict({"type": theirs, "max_depth": 6}), 4 * spp, range(1000, 1000 + k))
    assert np.isfinite(a).all()
    result = compare(a, b, tiles=3)
    print(ours, theirs, result)
    assert result.mean_b > 0, "reference image is black: the scene does not test anything"
    assert result.max_abs < 4, str(result)
    if channels:  # no channel may be off on its own (wavelengths and their weights)
        for c in range(3):
            one = compare(np.repeat(a[..., c:c + 1], 3, -1), np.repeat(b[..., c:c + 1], 3, -1), tiles=3)
            print(f"  channel {c}: {one}")
            assert one.max_abs < 4, f"channel {c}: {one}"
    return result


# --- spectral -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("scene_file", ["cornell.xml", "emitter_spot.xml"])
def test_spectral_bdpt_agrees_with_path(scene_file):
    """An area light and a spot light (delta position, falloff): light sub-paths carry the camera lane's
    wavelengths, emission re-evaluated there."""
    mi.set_variant("llvm_ad_spectral")
    agree(load(scene_file), "segment_bdpt", "path", channels=True)


def test_spectral_light_tracer_agrees_with_ptracer():
    mi.set_variant("llvm_ad_spectral")
    agree(load("cornell.xml"), "segment_lt", "ptracer", channels=True)


def test_emitted_weight_is_sample_emitter_rays_own_in_rgb():
    """The weight spectral light sub-paths get (emission at given wavelengths over the position and direction
    densities) is exactly ``sample_emitter_ray``'s where the wavelengths do not matter: every emitter type."""
    from segmitsuba.estimators.bdpt import EmitterTerms

    names = sorted(p.name for p in SCENES.glob("*.xml") if p.name not in ("medium.xml", "textured.xml"))
    n = 4096
    for name in names:
        scene = load(name, res=8)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(7, n)
        s1, s2, s3 = sampler.next_1d(), sampler.next_2d(), sampler.next_2d()
        ray, weight, emitter = scene.sample_emitter_ray(mi.Float(0), s1, s2, s3, True)
        ours = EmitterTerms(scene).emitted_weight(ray, emitter, s2, dr.full(mi.Bool, True, n))
        a, b = np.array(weight), np.array(ours)
        rel = np.abs(b - a) / np.maximum(np.abs(a), 1e-12)
        assert np.all((a == 0) == (b == 0)), name
        # (a spot light's falloff edge is steep: float round-off in the direction moves a few lanes by 0.5%)
        # (and an environment map's texel interpolation, seen from a sampled texel or a direction, by 1e-4)
        assert np.quantile(rel, 0.99) < 1e-4 and rel.max() < 1e-2, f"{name}: {rel.max()}"
        assert abs(b.mean() / a.mean() - 1) < 1e-5, name


# --- sensors --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("ours, theirs", [("segment_lt", "ptracer"), ("segment_bdpt", "path")])
def test_thinlens(ours, theirs):
    agree(with_sensor("cornell.xml", "thinlens"), ours, theirs)


def test_thinlens_light_tracing_density_is_the_camera_rays():
    """The MIS weight of light tracing (c = 1) needs, at every camera sub-path's first vertex, the density with
    which light tracing would have sampled the same lens point: the sample that picks the camera ray's own
    lens point must give back the camera ray."""
    from segmitsuba.estimators.bdpt import BidirectionalEstimator
    from segmitsuba.film import prepare_sampler
    from segmitsuba.samplers.camera import sample_camera_rays
    from segmitsuba.samplers.walk import SegmentState

    scene = with_sensor("cornell.xml", "thinlens")
    sensor = scene.sensors()[0]
    sampler = prepare_sampler(sensor, 0, 4, RES * RES * 4)
    ray, _, _ = sample_camera_rays(sensor, sampler, 4)
    si = scene.ray_intersect(ray)
    n = dr.width(ray.o)
    seg = SegmentState(origin=ray.o, origin_n=mi.Normal3f(0), direction=ray.d, chain=mi.Spectrum(1),
                       lead=mi.Spectrum(1), private=dr.full(mi.Bool, False, n), index=dr.zeros(mi.UInt32, n),
                       pdf=dr.full(mi.Float, 1.0, n), straight=dr.full(mi.Bool, True, n),
                       absorbed=dr.full(mi.Bool, False, n), sharp=dr.full(mi.Bool, True, n))
    estimator = BidirectionalEstimator(scene, sensor, sampler, 6, False, n, None, None)
    ds, importance = sensor.sample_direction(si, estimator._lens_sample(seg), si.is_valid())
    valid = np.array(si.is_valid())
    assert valid.mean() > 0.9 and np.all(np.array(ds.pdf)[valid] > 0)
    err = np.array(dr.norm(ds.d + ray.d))[valid]  # ds.d points from the vertex to the lens point
    assert err.max() < 1e-4, err.max()
    assert np.all(np.array(importance)[..., valid] > 0)


def test_orthographic_bdpt_agrees_with_path():
    """No light tracing with a delta-direction sensor: the other techniques cover its paths."""
    agree(with_sensor("cornell.xml", "orthographic"), "segment_bdpt", "path")


@functools.lru_cache
def _path_reference(kind: str) -> np.ndarray:
    """``path`` at 8192 spp through sensor ``kind`` (cornell 32x32), rendered once for both filters."""
    scene = with_sensor("cornell.xml", kind, res=32)
    return np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 8}), spp=8192,
                              seed=7))[..., :3]


@pytest.mark.parametrize("kind", ["thinlens", "orthographic"])
@pytest.mark.parametrize("method", ["segment_pf", "segment_bdf"])
def test_filters_agree_with_path_through_other_sensors(method, kind):
    """The filters start their camera walks with the sensor's own rays and never light-trace to it, so a thin
    lens and an orthographic sensor change nothing but the view. Biased estimators: mean ratio and relMSE
    against path (8192 spp) at a fixed kernel, as tests/test_filters_vs_references.py. Measured (kernel 0.1,
    2 x 64 spp, mean ratio / trimmed relMSE): pf thinlens 0.993 / 0.0024, orthographic 0.984 / 0.0022; bdf
    0.990 / 0.0021, 0.980 / 0.0014 (perspective 0.989); at kernel 0.05 bdf gives 0.996 / 0.994 (perspective
    0.999): the kernel's bias, as with a pinhole."""
    scene = with_sensor("cornell.xml", kind, res=32)
    ref = _path_reference(kind)
    integrator = {"type": method, "kernel_size": 0.1, "alpha": 1.0}
    images = [np.array(mi.render(scene, integrator=mi.load_dict(integrator), spp=64, seed=s))[..., :3]
              for s in range(2)]
    ratio = np.mean([img.mean() for img in images]) / ref.mean()
    trimmed = [np.sort(((img - ref) ** 2 / (ref**2 + 1e-2)).ravel())[: int(0.99 * img.size)] for img in images]
    error = np.mean([t.mean() for t in trimmed])  # 1% trimmed, as the stored-reference tests
    print(method, kind, ratio, error)
    assert abs(ratio - 1) < 0.035 and error < 0.0045, (ratio, error)


def test_orthographic_is_refused_by_the_light_tracer():
    scene = with_sensor("cornell.xml", "orthographic", res=8)
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=mi.load_dict({"type": "segment_lt"}), spp=1)
    chain = error_chain(info.value).split(" | ")
    assert any("segment_lt" in m and "OrthographicCamera" in m for m in chain), chain


# --- sensors that measure one pixel -------------------------------------------------------------------------

def _meter_scene(kind: str) -> mi.Scene:
    """A floor, a box on it and a square light above, seen by one ``kind`` sensor with a 1x1 film (the
    irradiance meter is the floor's)."""
    film = {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
    T = mi.ScalarTransform4f
    scene = {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
        "box": {"type": "cube", "to_world": T().translate([0.5, 0.3, 0]).scale(0.3),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.5, 0.7]}}},
        "light": {"type": "rectangle", "to_world": T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(1.5),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 4}}},
    }
    if kind == "irradiancemeter":
        scene["floor"]["sensor"] = {"type": "irradiancemeter", "film": film}
    elif kind == "radiancemeter":
        scene["sensor"] = {"type": "radiancemeter", "origin": [0, 2.5, 3], "direction": [0, -2.5, -3], "film": film}
    else:
        scene["sensor"] = {"type": kind, "direction": [0, -1, -0.3], "film": film}
    return mi.load_dict(scene)


@pytest.mark.parametrize("kind", ["radiancemeter", "irradiancemeter", "distant"])
def test_sensors_that_measure_one_pixel(kind):
    """A radiance meter, an irradiance meter and a distant sensor: segment_pt and segment_bdpt agree with
    Mitsuba's path (z-test over seeds; the irradiance meter's rays come through ``sample_ray_differential``, the
    only one it implements); the light tracer and the filters refuse them by name (the filters rendered a
    radiance meter 0.09-0.8x of path, the light tracer the irradiance meter 22x, as Mitsuba's ptracer)."""
    scene = _meter_scene(kind)
    assert scene.sensors()[0].class_name() in ("RadianceMeter", "IrradianceMeter", "DistantSensorImpl")
    reference = render_seeds(scene, mi.load_dict({"type": "path", "max_depth": 4}), 4096, range(1000, 1008))
    for ours in ("segment_pt", "segment_bdpt"):
        images = render_seeds(scene, mi.load_dict({"type": ours, "max_depth": 4}), 1024, range(8))
        assert np.isfinite(images).all()
        result = compare(images, reference, tiles=1)
        print(kind, ours, result)
        assert result.mean_b > 0.05, "the sensor sees no light: the scene tests nothing"
        assert result.max_abs < 4, (ours, str(result))
    for refused, words in (("segment_lt", "light tracing needs"), ("segment_mvf", "measures one pixel"),
                           ("segment_bdf", "measures one pixel")):
        with pytest.raises(Exception) as info:
            mi.render(scene, integrator=mi.load_dict({"type": refused}), spp=4)
        chain = error_chain(info.value)
        assert refused in chain and words in chain and scene.sensors()[0].class_name() in chain, chain


# --- develop=False ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("integrator, scene_file", [("segment_bdpt", "cornell.xml"), ("segment_bdf", "cornell.xml"),
                                                     ("segment_bdf", "caustic.xml")])
def test_develop_false_leaves_the_image_in_the_film(integrator, scene_file):
    """As Mitsuba's path and ptracer: render(develop=False) returns an empty tensor and the sensor's film
    develops later to the image render(develop=True) returns (camera samples and light-tracing splats
    together, with a gaussian filter's border coverage and a crop window). On the caustic scene segment_bdf
    splats its caustic segments to the sensor too (docs/maths.md §4.11)."""
    crop = ('<rfilter type="gaussian"/><integer name="crop_offset_x" value="4"/>'
            '<integer name="crop_offset_y" value="2"/><integer name="crop_width" value="16"/>'
            '<integer name="crop_height" value="12"/>')
    xml = (SCENES / scene_file).read_text()
    xml = xml.replace('<rfilter type="box"/>', crop, 1) if '<rfilter type="box"/>' in xml else xml.replace(
        '<string name="pixel_format" value="rgb"/>', '<string name="pixel_format" value="rgb"/>' + crop, 1)
    xml = xml.replace('<string name="pixel_format" value="rgb"/>', '<string name="pixel_format" value="rgba"/>')
    scene = mi.load_string(xml, res=24)
    sensor = scene.sensors()[0]
    # segment_bdf: its camera samples of direct light apart from the pool fill a block of their own
    integrator = mi.load_dict({"type": integrator})
    image = np.array(integrator.render(scene, sensor, seed=3, spp=4))
    empty = integrator.render(scene, sensor, seed=3, spp=4, develop=False)
    assert dr.width(empty) == 0
    later = np.array(sensor.film().develop())
    assert later.shape == image.shape == (12, 16, 4)
    assert np.abs(later - image).max() <= 1e-5 * np.abs(image).max(), np.abs(later - image).max()
    assert image[..., :3].mean() > 0.01
