"""One render, one kernel schedule: the filters' kernel follows the whole render however it is split into
``mi.render`` calls (docs/maths.md §5; the Dask case is in test_distributed.py)."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES, lattice_budget

from segmitsuba.film import film_lattice, film_sample_count, prepare_sampler
from segmitsuba.references import load_reference, relmse
from segmitsuba.rendering import render_passes
from segmitsuba.samplers.camera import sample_camera_rays
from segmitsuba.schedule import kernel_size_at, pass_seed

RES = 32


def box_cornell(res: int = RES) -> dict:
    """Cornell box with a box filter: every pixel then averages exactly its own samples, so a render split
    into passes is the same image as one call wherever the passes draw the same pools."""
    d = mi.cornell_box()
    d["sensor"]["film"].update({"width": res, "height": res, "rfilter": {"type": "box"}})
    return d


def test_kernel_size_is_the_product_rule_and_extends_it_between_pools():
    r0, alpha = 0.3, 0.67
    r2 = r0 * r0
    for i in range(12):
        assert kernel_size_at(r0, alpha, i) == pytest.approx(math.sqrt(r2), rel=1e-12)
        r2 *= (i + alpha) / (i + 1)
    sizes = [kernel_size_at(r0, alpha, i / 4) for i in range(40)]
    assert all(a > b for a, b in zip(sizes, sizes[1:], strict=False))  # strictly shrinking, also between pools
    assert kernel_size_at(r0, 1.0, 17.5) == r0
    with pytest.raises(ValueError, match="pool index"):
        kernel_size_at(r0, alpha, -1)


def glass_cornell(res: int = RES) -> dict:
    """:func:`box_cornell` with a glass sphere: its caustic segments are also connected to the sensor, into the
    light block (docs/maths.md §4.11)."""
    d = box_cornell(res)
    d["glass"] = {"type": "sphere", "center": [0.3, -0.6, 0.2], "radius": 0.35, "bsdf": {"type": "dielectric"}}
    return d


@pytest.mark.parametrize("make_scene", [box_cornell, glass_cornell])
def test_one_call_and_passes_of_one_pool_render_the_same_pools(make_scene):
    scene = mi.load_dict(make_scene())
    integrator = mi.load_dict({"type": "segment_bdf"})
    one = np.array(mi.render(scene, integrator=integrator, spp=16, seed=3))
    pools = integrator.last_stats["pools"]
    assert [p["spp"] for p in pools] == [4] * 4 and [p["spp_offset"] for p in pools] == [0, 4, 8, 12]
    r0 = integrator.last_stats["kernel_size"]
    assert [p["kernel_size"] for p in pools] == pytest.approx([kernel_size_at(r0, 0.67, i) for i in range(4)])
    assert [p["seed"] for p in pools] == [pass_seed(3, i) for i in range(4)]

    split = render_passes(scene, integrator, spp=16, pass_spp=4, seed=3, progress=False)
    assert split.pools == pools  # offsets, seeds and kernel sizes of the whole render
    assert integrator.spp_offset == 0  # the engine leaves the integrator as it found it
    np.testing.assert_allclose(split.image, one, rtol=1e-4, atol=1e-6)

    # A user's own loop, as the plugin docstring shows it, continues the same schedule.
    acc = 0.0
    for k in range(4):
        integrator.spp_offset = 4 * k
        acc = acc + np.array(mi.render(scene, integrator=integrator, spp=4, seed=pass_seed(3, k)))
        assert integrator.last_stats["pools"] == [pools[k]]
    integrator.spp_offset = 0
    np.testing.assert_allclose(acc / 4, one, rtol=1e-4, atol=1e-6)
    if make_scene is glass_cornell:  # the light block is really there: without it the image changes
        plain = mi.load_dict({"type": "segment_bdf", "light_tracing": False})
        assert np.abs(np.array(mi.render(scene, integrator=plain, spp=16, seed=3)) - one).max() > 1e-3


@pytest.mark.parametrize("make_scene", [box_cornell, glass_cornell])
def test_pools_of_film_lattices_keep_the_schedule_and_split_by_samples_per_pixel(make_scene):
    """Where one sample per pixel exceeds ``memory_budget``, each sample per pixel is split into pools of one film
    lattice each (docs/maths.md §5.7): their positions in the render count every lattice's pool, their kernel is
    wider by the lattice's spacing, and a render split into calls of whole samples per pixel draws the same pools
    (the light splats of the glass' caustic included)."""
    scene = mi.load_dict(make_scene())
    budget = lattice_budget(scene, 4)
    integrator = mi.load_dict({"type": "segment_bdf", "memory_budget": budget})
    one = np.array(mi.render(scene, integrator=integrator, spp=3, seed=3))
    stats = integrator.last_stats
    pools = stats["pools"]
    assert (stats["pool_groups"], stats["pool_spp"], stats["passes"]) == (4, 1, 12)
    assert [p["lattice"] for p in pools] == [0, 1, 2, 3] * 3
    assert [p["spp_offset"] for p in pools] == [0] * 4 + [1] * 4 + [2] * 4
    r0 = stats["kernel_size"]
    assert r0 == pytest.approx(2 * mi.load_dict({"type": "segment_bdf"}).initial_kernel_size(scene, scene.sensors()[0]))
    assert [p["kernel_size"] for p in pools] == pytest.approx([kernel_size_at(r0, 0.67, i) for i in range(12)])
    assert [p["seed"] for p in pools] == [pass_seed(pass_seed(3, u), g) for u in range(3) for g in range(4)]
    assert np.isfinite(one).all()

    split = render_passes(scene, integrator, spp=3, pass_spp=1, seed=3, progress=False)
    assert split.pools == pools
    np.testing.assert_allclose(split.image, one, rtol=1e-4, atol=1e-6)
    # a sparse lattice pool's warning points to the budget, not to spp_per_pass (which cannot fit)
    from segmitsuba import SparsePoolWarning

    with pytest.warns(SparsePoolWarning, match="larger memory_budget"):
        mi.render(scene, integrator=mi.load_dict({"type": "segment_bdf", "memory_budget": budget,
                                                  "kernel_scale": 0.01}), spp=1, seed=3)
    # a time budget stops between samples per pixel, never between the lattices of one
    hurried = mi.load_dict({"type": "segment_bdf", "memory_budget": budget, "time_budget": 1e-6})
    mi.render(scene, integrator=hurried, spp=3, seed=3)
    assert (hurried.last_stats["passes"], hurried.last_stats["spp"]) == (4, 1)


@pytest.mark.parametrize("groups", [2, 4, 8, 16])
def test_film_lattices_split_the_film_samples(groups):
    """The lattices of a film (its sampled border included) are disjoint and cover every film sample."""
    film = mi.load_dict({"type": "hdrfilm", "width": 13, "height": 7, "rfilter": {"type": "gaussian"}})
    parts = [np.array(film_lattice(film, groups, g)) for g in range(groups)]
    assert all(len(p) for p in parts)
    assert sorted(np.concatenate(parts).tolist()) == list(range(film_sample_count(film)))
    with pytest.raises(ValueError, match="power of two"):
        film_lattice(film, 6, 0)
    # the camera samples of the lattices' pools land in every pixel once
    sensor = mi.load_dict(box_cornell(12)["sensor"])
    film = sensor.film()
    seen = np.zeros(film_sample_count(film), dtype=int)
    for g in range(groups):
        pixels = film_lattice(film, groups, g)
        _, _, pos = sample_camera_rays(sensor, prepare_sampler(sensor, g, 1, dr.width(pixels)), 1, pixels=pixels)
        np.add.at(seen, np.array(pos.y, dtype=int) * 12 + np.array(pos.x, dtype=int), 1)
    assert (seen == 1).all()


def test_calls_of_several_pools_keep_the_schedule():
    """Passes of 8 spp hold two pools each: their seeds differ from one call's, their kernel sizes do not."""
    scene = mi.load_dict(box_cornell(16))
    integrator = mi.load_dict({"type": "segment_pf", "spp_per_pass": 2})
    mi.render(scene, integrator=integrator, spp=16, seed=1)
    one = integrator.last_stats["pools"]
    split = render_passes(scene, integrator, spp=16, pass_spp=8, seed=1, progress=False)
    assert [p["kernel_size"] for p in split.pools] == [p["kernel_size"] for p in one]
    assert [p["spp_offset"] for p in split.pools] == list(range(0, 16, 2))
    # A pass smaller than a pool lies between pools: its size is between its neighbours'.
    odd = render_passes(scene, integrator, spp=5, pass_spp=1, seed=1, progress=False).pools
    sizes = [p["kernel_size"] for p in odd]
    assert sizes[0] == one[0]["kernel_size"] and sizes[2] == pytest.approx(one[1]["kernel_size"])
    assert sizes[0] > sizes[1] > sizes[2] > sizes[3] > sizes[4]


def test_a_render_in_4_spp_passes_converges_at_the_one_call_rate():
    """relMSE against the stored reference falls with spp (16 -> 256) as steeply through render_passes
    with 4-spp passes as in one mi.render call of each spp. (Beyond ~1000 spp the split's own floor shows: with
    the scene's gaussian filter each call's film normalizes by its own filter weights, ~0.5% per pixel.)"""
    scene = mi.load_file(str(SCENES / "emitter_area.xml"), res=RES)
    ref = load_reference("emitter_area")[0][..., :3]
    integrator = mi.load_dict({"type": "segment_bdf"})
    counts = (16, 64, 256)
    seeds = (11, 12, 13)  # one seed's relMSE at 16 spp moves by a fifth: the slopes compare means
    split = {n: 0.0 for n in counts}

    def checkpoint(report) -> None:
        if report.spp in counts:
            split[report.spp] += relmse(report.image()[..., :3], ref) / len(seeds)

    for seed in seeds:
        render_passes(scene, integrator, spp=counts[-1], pass_spp=4, seed=seed, progress=False, callback=checkpoint)
    one = {n: np.mean([relmse(np.array(mi.render(scene, integrator=integrator, spp=n, seed=seed + n))[..., :3], ref)
                       for seed in seeds]) for n in counts}
    slope_split = np.polyfit(np.log(counts), np.log([split[n] for n in counts]), 1)[0]
    slope_one = np.polyfit(np.log(counts), np.log([one[n] for n in counts]), 1)[0]
    assert slope_one < -0.2, one  # the error really falls: the kernel shrinks over the render
    # Over three seeds the 16-spp means move by about 12%, the slopes by about 0.05 each. A split whose kernel
    # does not shrink over the render falls at -0.18 here, against -0.55 to -0.65 when it does.
    assert abs(slope_split - slope_one) < 0.15, (split, one)
