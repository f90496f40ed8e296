"""The benchmark scenes load, and Mitsuba's path renders them without NaN/Inf and not black."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES


@pytest.mark.parametrize("name", ["sds", "veach_glossy"])
def test_scene_renders_with_path(name: str):
    scene = mi.load_file(str(SCENES / f"{name}.xml"), res=24, max_depth=8)
    image = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 8}), spp=8, seed=1))
    assert image.shape == (24, 24, 3)
    assert np.isfinite(image).all() and image.min() >= 0
    assert image.mean() > 0.05, f"{name}: mean {image.mean():.4f}"
    assert np.mean(image.max(axis=2) > 1e-3) > 0.9, f"{name}: the fill light leaves black pixels"


def test_sds_caustic_needs_the_glass():
    """The sds caustic is light focused by the glass sphere: with the sphere, a bright spot (pixels 17-18,
    15-16 at 32x32) sits inside the sphere's darker shadow; without it (a null BSDF) the floor under the slab is
    lit evenly by the light through the slab."""
    text = (SCENES / "sds.xml").read_text()
    sphere = '<ref id="glass_mat"/>\n    </shape>\n\n    <!-- Thin'
    assert text.count(sphere) == 1
    scenes = [mi.load_string(t, res=32, max_depth=8) for t in (text, text.replace(sphere, sphere.replace(
        '<ref id="glass_mat"/>', '<bsdf type="null"/>')))]
    integrator = mi.load_dict({"type": "path", "max_depth": 8})
    with_glass, without = (np.array(mi.render(s, integrator=integrator, spp=512, seed=2 + i)).mean(-1)
                           for i, s in enumerate(scenes))
    assert np.isfinite(with_glass).all() and np.isfinite(without).all()
    spot, shadow = (slice(17, 19), slice(15, 17)), (slice(20, 22), slice(12, 20))
    assert with_glass[spot].mean() > 3 * without[spot].mean(), (with_glass[spot], without[spot])
    assert with_glass[shadow].mean() < 0.8 * without[shadow].mean(), (with_glass[shadow], without[shadow])
