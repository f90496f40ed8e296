"""Registration, property validation and refused scene features of the sequential integrators."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES, small_cornell

import segmitsuba

INTEGRATORS = ["segment_pt", "segment_lt", "segment_bdpt", "segment_mvf", "segment_pf", "segment_bdf"]


def error_chain(exc: BaseException) -> str:
    """Messages of an exception and its causes (mi.render wraps integrator errors)."""
    parts = []
    while exc is not None:
        parts.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return " | ".join(parts)


@pytest.mark.parametrize("name", INTEGRATORS)
@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral", "llvm_ad_mono"])
def test_renders_in_every_llvm_variant(name, variant):
    mi.set_variant(variant)
    scene = mi.load_dict(small_cornell())
    img = np.array(mi.render(scene, integrator=mi.load_dict({"type": name}), spp=4))
    assert img.shape[:2] == (16, 16)
    assert np.isfinite(img).all()
    assert img.mean() > 0.01


@pytest.mark.parametrize("name", INTEGRATORS)
def test_sunsky_is_refused_where_its_sampling_matters(name):
    """Mitsuba's sunsky samples light that its radiance does not match (its own ptracer renders 0.2x path):
    refused, naming it, by every integrator whose estimate weighs or traces its samples; segment_pt renders it as
    path does."""
    d = small_cornell(8)
    d.pop("light")
    d["sky"] = {"type": "sunsky"}
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": name})
    if name == "segment_pt":
        img = np.array(mi.render(scene, integrator=integrator, spp=64, seed=1))
        ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=64, seed=1))
        assert img.mean() == pytest.approx(ref.mean(), rel=1e-3)  # the same samples, summed in another order
        return
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=integrator, spp=1)
    assert f"{name}: emitter" in error_chain(info.value) and "sunsky" in error_chain(info.value)


def _merged_floor_and_wall(sky: dict) -> dict:
    t = mi.ScalarTransform4f()
    bsdf = {"type": "diffuse"}
    return {
        "type": "scene", "sky": sky,
        "sensor": {"type": "perspective", "to_world": t.look_at(origin=[0, 0, 3.5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": t.translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(2),
                  "bsdf": bsdf},
        "wall": {"type": "rectangle", "to_world": t.translate([0, 0, -1]).scale(2), "bsdf": dict(bsdf)}}


@pytest.mark.parametrize("sky", ["constant", "directional"])
@pytest.mark.parametrize("name", INTEGRATORS)
def test_sky_light_reaches_a_scene_whose_box_misses_a_merged_mesh(name, sky):
    """Mitsuba merges shapes that share a BSDF into one mesh, whose bounding box can be that of its first part:
    here a floor and a wall, merged, leave the scene's box invalid, and environment and directional emitters
    emit across that box (Mitsuba's ptracer rendered the constant sky black, 2e-9 of path, and so did segment_lt
    and segment_bdpt). The emitters get a sphere that holds the shapes, and every integrator renders what path
    renders."""
    emitter = ({"type": "constant", "radiance": 1.0} if sky == "constant" else
               {"type": "directional", "direction": [0.3, -1, -0.4], "irradiance": 2.0})
    scene = mi.load_dict(_merged_floor_and_wall(emitter))
    assert not scene.bbox().valid()  # the merged mesh's box (Mitsuba 3.9); if this changes, the test is moot
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 4}), spp=1024))
    img = np.mean([np.array(mi.render(scene, integrator=mi.load_dict({"type": name, "max_depth": 4}), spp=64,
                                      seed=seed)) for seed in range(4)], axis=0)
    assert np.isfinite(img).all()
    assert img[..., :3].mean() == pytest.approx(ref[..., :3].mean(), rel=0.05)


@pytest.mark.parametrize("name", INTEGRATORS)
def test_textured_light_on_a_mesh_with_overlapping_charts_is_refused(name):
    """Mitsuba samples a bitmap-textured area light's positions through the inverse of its mesh's texture
    parameterization, which on a cube (six faces on one unit square) reaches one face only: its path renders 0.80x
    and its ptracer 0.19x of what BSDF sampling alone gives. Refused, naming the mesh, where its emitter samples are
    weighed or traced; segment_pt renders what path renders. The same light on a rectangle renders."""
    texture = {"type": "bitmap", "filename": str(SCENES / "textures" / "checker_light.exr")}
    d = small_cornell(8)
    d["light"] = {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0, 0.8, 0]).scale(0.15),
                  "emitter": {"type": "area", "radiance": texture}}
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": name})
    if name == "segment_pt":
        img = np.array(mi.render(scene, integrator=integrator, spp=64, seed=1))
        ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=64, seed=1))
        assert img.mean() == pytest.approx(ref.mean(), rel=1e-3)
    else:
        with pytest.raises(Exception) as info:
            mi.render(scene, integrator=integrator, spp=1)
        assert "mesh 'light'" in error_chain(info.value) and "6 times" in error_chain(info.value)
    d["light"]["type"] = "rectangle"
    d["light"]["to_world"] = mi.ScalarTransform4f().translate([0, 0.8, 0]).rotate([1, 0, 0], 90).scale(0.2)
    img = np.array(mi.render(mi.load_dict(d), integrator=integrator, spp=4))
    assert np.isfinite(img).all() and img.mean() > 0


@pytest.mark.parametrize("name", INTEGRATORS)
def test_samplers_that_round_their_sample_count_render(name):
    """Mitsuba's orthogonal sampler rounds 16 samples per pixel to 25 (a prime squared), and stratified ones round
    a pool's 2 or 3 to 4: cloned for a pass or pool of another count they failed ("sample_count should be a
    multiple of samples_per_wavefront"). Such passes use an independent sampler, with a warning."""
    d = small_cornell(8)
    d["sensor"]["sampler"] = {"type": "orthogonal", "sample_count": 16}
    scene = mi.load_dict(d)
    with pytest.warns(RuntimeWarning, match="OrthogonalSampler cannot generate"):
        img = np.array(mi.render(scene, integrator=mi.load_dict({"type": name}), spp=16, seed=1))
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path"}), spp=256, seed=1))
    assert np.isfinite(img).all()
    assert img.mean() == pytest.approx(ref.mean(), rel=0.25)  # 16 spp at 8x8: this checks it renders, not noise


@pytest.mark.parametrize("name", INTEGRATORS)
def test_polarized_variant_is_refused_clearly(name):
    mi.set_variant("llvm_ad_mono_polarized")
    with pytest.raises(Exception, match="polarized transport is not supported"):
        mi.load_dict({"type": name})


@pytest.mark.parametrize("name", INTEGRATORS)
def test_scalar_variant_is_refused_clearly(name):
    mi.set_variant("scalar_rgb")
    with pytest.raises(Exception, match="JIT variant"):
        mi.load_dict({"type": name})


def test_registration_for_variants_set_after_import():
    code = (
        "import segmitsuba, mitsuba as mi\n"
        "assert mi.variant() is None\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        "print(mi.load_dict({'type': 'segment_pt'}))\n"
        "mi.set_variant('llvm_ad_spectral')\n"
        "print(mi.load_dict({'type': 'segment_lt'}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "SegmentPathTracer" in out.stdout and "SegmentLightTracer" in out.stdout


def test_llvm_guard_sets_path_before_drjit():
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    code = "import segmitsuba, os, drjit as dr; print(os.environ['DRJIT_LIBLLVM_PATH'], dr.detail.llvm_version()[0])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    path, major = out.stdout.split()
    assert int(major) >= 16 and "LLVM" in path


def test_llvm_guard_explains_a_broken_llvm():
    old = [p for p in ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", "/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1")
           if os.path.exists(p)]
    if not old:
        pytest.skip("no libLLVM < 16 on this machine to test the guard with")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=old[0])
    code = "import drjit\nimport segmitsuba\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode != 0
    assert "libllvm19" in out.stderr and "DRJIT_LIBLLVM_PATH" in out.stderr


def test_llvm_guard_warns_where_only_an_old_llvm_is_installed():
    from segmitsuba._llvm import missing_llvm_warning

    message = missing_llvm_warning([14, 15], avx512=True)
    assert "version 15" in message and "libllvm19" in message
    assert missing_llvm_warning([15], avx512=False) is None  # LLVM 15 works without AVX-512
    assert missing_llvm_warning([], avx512=True) is None  # Dr.Jit says itself that it finds no LLVM


@pytest.mark.parametrize("name", INTEGRATORS)
@pytest.mark.parametrize("props, message", [
    ({"max_depth": -2}, "max_depth"),
    ({"max_depth": 2.5}, "integer"),
    ({"rr_depth": 0}, "rr_depth"),
    ({"hide_emitters": 1}, "boolean"),
])
def test_invalid_properties_are_named(name, props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": name, **props})


@pytest.mark.parametrize("props, message", [
    ({"type": "segment_bdf", "glossy_vertices": "sometimes"}, "glossy_vertices"),
    ({"type": "segment_bdf", "glossy_vertices": "private", "direct_light": "filtered"}, "direct_light"),
    ({"type": "segment_mvf", "glossy_vertices": "private", "direct_light": "filtered"}, "direct_light"),
    # camera walks that stop at their first vertex cannot carry a glossy vertex's light: no such property
    ({"type": "segment_pf", "glossy_vertices": "private"}, "glossy_vertices"),
])
def test_glossy_vertices_property_is_checked(props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict(props)
    if props["type"] != "segment_pf":
        defaults = {light: mi.load_dict({"type": props["type"], "direct_light": light}).glossy_vertices
                    for light in ("sampled", "mis", "filtered")}
        assert defaults == {"sampled": "private", "mis": "private", "filtered": "filtered"}


@pytest.mark.parametrize("name", INTEGRATORS)
def test_unknown_property_is_refused(name):
    with pytest.raises(Exception, match="max_dept"):
        mi.load_dict({"type": name, "max_dept": 3})


@pytest.mark.parametrize("name", INTEGRATORS)
def test_participating_media_are_refused(name):
    d = small_cornell()
    d["fog"] = {"type": "sphere", "radius": 0.3, "bsdf": {"type": "null"},
                "interior": {"type": "homogeneous", "sigma_t": 1.0, "albedo": 0.5}}
    scene = mi.load_dict(d)
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=mi.load_dict({"type": name}), spp=1)
    assert re.search("participating media are not supported yet.*fog", error_chain(info.value))


@pytest.mark.parametrize("name", INTEGRATORS)
def test_scene_without_emitters_renders_black(name):
    d = small_cornell()
    d["light"].pop("emitter")
    scene = mi.load_dict(d)
    assert len(scene.emitters()) == 0
    img = np.array(mi.render(scene, integrator=mi.load_dict({"type": name}), spp=2))
    assert np.isfinite(img).all() and np.all(img[..., :3] == 0)


@pytest.mark.parametrize("name", INTEGRATORS)
def test_negative_spp_and_a_missing_sensor_are_named(name):
    """segment_bdf rendered spp=-2 as a black image; the others failed inside Mitsuba's bindings. (mi.render
    itself looks a sensor index up; the integrators' own render names one out of range.)"""
    scene = mi.load_dict(small_cornell(res=8))
    integrator = mi.load_dict({"type": name})
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=integrator, spp=-2)
    chain = error_chain(info.value)
    assert name in chain and "spp must be >= 0" in chain, chain
    with pytest.raises(ValueError, match=f"{name}: sensor index 3 is out of range"):
        integrator.render(scene, sensor=3, spp=1)


@pytest.mark.parametrize("name", INTEGRATORS)
def test_nesting_in_aov_or_moment_is_refused_and_a_uint32_seed_renders(name):
    """Mitsuba's aov and moment integrators ask their inner integrator for one ray at a time, which ours cannot
    answer (they failed with 'tried to call a pure virtual function', or on the UInt32 seed the aov integrator
    passes); mi.render's UInt32 seed renders what the int seed renders."""
    scene = mi.load_dict(small_cornell(res=4))
    for outer in ("aov", "moment"):
        spec = {"type": outer, "inner": {"type": name}}
        if outer == "aov":
            spec["aovs"] = "dd.y:depth"
        with pytest.raises(Exception) as info:
            mi.render(scene, integrator=mi.load_dict(spec), spp=2)
        chain = error_chain(info.value)
        assert name in chain and "one ray at a time" in chain, chain
    integrator = mi.load_dict({"type": name})
    a = np.array(mi.render(scene, integrator=integrator, spp=4, seed=mi.UInt32(5)))
    b = np.array(mi.render(scene, integrator=integrator, spp=4, seed=5))
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6), np.abs(a - b).max()


@pytest.mark.parametrize("name", INTEGRATORS)
def test_camera_rays_that_all_leave_the_scene(name):
    """A sky and no shape: every camera ray leaves the scene, so a filter's pools hold no surface point and
    their grids no cluster (the filters failed on an empty array); the image is the sky. On a 1x1 film, whose
    probe pools of one sample often have no surface point either, the camera-side integrators render path's
    value (box filter, the light hidden: a low-variance mean) and the filters, whose derived kernel is then wider
    than the scene, warn that they are biased far beyond a blur."""
    sensor = {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}}
    sky = mi.load_dict({"type": "scene", "sensor": sensor, "sky": {"type": "constant", "radiance": 0.7}})
    img = np.array(mi.render(sky, integrator=mi.load_dict({"type": name}), spp=4))
    if name == "segment_lt":  # no surface for light to leave from: only the sky the sensor sees, splatted
        assert np.isfinite(img).all()
        return
    assert np.allclose(img[..., :3], 0.7, rtol=1e-5), img[..., :3].mean()
    d = small_cornell(res=1)
    d["sensor"]["film"]["rfilter"] = {"type": "box"}
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": name, "hide_emitters": True})
    filters = name in ("segment_mvf", "segment_pf", "segment_bdf")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # the filters' image is only checked for being finite: one render of a few samples
        ours = np.mean([np.array(mi.render(scene, integrator=integrator, spp=16 if filters else 256, seed=s))
                        for s in range(1 if filters else 4)])
    assert np.isfinite(ours)
    kernel_warnings = [w for w in caught if issubclass(w.category, segmitsuba.KernelSizeWarning)]
    if filters:
        assert len(kernel_warnings) == 1 and "wider than the whole scene" in str(kernel_warnings[0].message)
        return
    assert not kernel_warnings
    path = mi.load_dict({"type": "path", "hide_emitters": True})
    ref = np.mean([np.array(mi.render(scene, integrator=path, spp=4096, seed=99 + s)) for s in range(2)])
    assert abs(ours / ref - 1) < 0.06, (ours, ref)


@pytest.mark.parametrize("name", ["segment_pt", "segment_lt", "segment_bdpt"])  # filters need max_depth >= 1
def test_max_depth_zero_is_black_and_one_shows_only_emitters(name):
    scene = mi.load_dict(small_cornell())
    black = np.array(mi.render(scene, integrator=mi.load_dict({"type": name, "max_depth": 0}), spp=2))
    assert np.all(black[..., :3] == 0)
    emit = np.array(mi.render(scene, integrator=mi.load_dict({"type": name, "max_depth": 1}), spp=16))
    reference = {"segment_pt": "path", "segment_lt": "ptracer", "segment_bdpt": "path"}[name]
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": reference, "max_depth": 1}), spp=16))
    assert abs(emit.mean() - ref.mean()) < 0.05 * ref.mean()


def test_same_seed_is_deterministic_and_seeds_differ():
    scene = mi.load_dict(small_cornell())
    integ = mi.load_dict({"type": "segment_pt"})
    dr.set_thread_count(dr.thread_count())
    a = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
    b = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
    c = np.array(mi.render(scene, integrator=integ, spp=4, seed=4))
    # equal up to the order in which the two threads' atomic film splats (a filter wider than a pixel) add up
    assert np.allclose(a, b, rtol=1e-5, atol=1e-7)
    assert np.abs(a - c).max() > 1e3 * np.abs(a - b).max() + 1e-4
