"""segment_pt must agree with Mitsuba's path, and segment_lt with ptracer, on every scene (z-tests).

Both pairs are unbiased estimators of the same image, so over independent seeds the difference of their
mean image (and of each of 3x3 tiles' means) divided by its standard error follows Student's t, reported
as the equivalent normal z (tests/stats.py): |z| < 4 fails by chance with probability ~6e-5 per
comparison, ~1.5% for the whole file. The two methods use disjoint seed ranges, since
segment_pt and path draw the same random numbers for the same seed.
"""

from __future__ import annotations

import gc

import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES
from stats import compare, render_seeds

SCENE_FILES = sorted(p.name for p in SCENES.glob("*.xml") if p.name != "medium.xml")
PAIRS = [("segment_pt", "path"), ("segment_lt", "ptracer")]
K, SPP, RES = 8, 16, 32


def load(name: str, **defines) -> mi.Scene:
    return mi.load_file(str(SCENES / name), res=RES, **defines)


@pytest.mark.parametrize("ours, theirs", PAIRS)
@pytest.mark.parametrize("scene_file", SCENE_FILES)
def test_agrees_with_mitsuba(scene_file, ours, theirs):
    if scene_file == "textured.xml" and ours == "segment_lt":
        pytest.skip("checkerboard emitter: ptracer cannot render it (test_procedural_emitter_texture_emits)")
    scene = load(scene_file)
    a = render_seeds(scene, mi.load_dict({"type": ours, "max_depth": 6}), SPP, range(K))
    b = render_seeds(scene, mi.load_dict({"type": theirs, "max_depth": 6}), SPP, range(1000, 1000 + K))
    assert np.isfinite(a).all()
    result = compare(a, b, tiles=3)
    print(scene_file, ours, theirs, result)
    assert result.mean_b > 0, "reference image is black: the scene does not test anything"
    assert result.max_abs < 4, str(result)


def test_film_features_crop_alpha_and_filters():
    """Crop windows, an alpha channel and a non-box filter (gaussian) are honoured like path/ptracer do."""
    d = mi.cornell_box()
    d["sensor"]["film"] = {"type": "hdrfilm", "width": 48, "height": 40, "pixel_format": "rgba",
                           "crop_offset_x": 8, "crop_offset_y": 4, "crop_width": 32, "crop_height": 24,
                           "rfilter": {"type": "gaussian"}}
    scene = mi.load_dict(d)
    for ours, theirs in PAIRS:
        a = render_seeds(scene, mi.load_dict({"type": ours}), SPP, range(K))
        b = render_seeds(scene, mi.load_dict({"type": theirs}), SPP, range(1000, 1000 + K))
        assert a.shape == b.shape == (K, 24, 32, 4)
        result = compare(a, b, tiles=4)
        assert result.max_abs < 4, f"{ours}: {result}"
        if ours == "segment_pt":  # path's alpha is the coverage in [0, 1]
            alpha = compare(np.repeat(a[..., 3:4], 3, -1), np.repeat(b[..., 3:4], 3, -1), tiles=3)
            assert alpha.max_abs < 4, f"{ours} alpha: {alpha}"
        else:  # ptracer's alpha counts splatted vertices (depends on Russian roulette): only sanity
            assert np.isfinite(a[..., 3]).all() and a[..., 3].mean() > 0


def test_procedural_emitter_texture_emits():
    """Mitsuba cannot emit from textured.xml's checkerboard light (its ``sample_ray`` needs the texture's
    ``sample_spectrum``); ``segmitsuba.samplers.emission`` emits from it uniformly in area. textured_bitmap.xml
    is the same scene with the same checker as a bitmap, which Mitsuba emits from in proportion to radiance:
    light tracing gives the same image from both, two different samplers of one expectation."""
    scene = load("textured.xml")
    bitmap = load("textured_bitmap.xml")
    a = render_seeds(scene, mi.load_dict({"type": "segment_lt", "max_depth": 6}), SPP, range(K))
    b = render_seeds(bitmap, mi.load_dict({"type": "segment_lt", "max_depth": 6}), SPP, range(1000, 1000 + K))
    assert np.isfinite(a).all()
    result = compare(a, b, tiles=3)
    print(result)
    assert result.mean_b > 0
    assert result.max_abs < 4, str(result)
    # Dr.Jit traces virtual calls over every live emitter: a live checkerboard emitter would break light
    # tracing in other scenes of this process (Mitsuba's ptracer too), so release it now.
    del scene, bitmap
    gc.collect()
