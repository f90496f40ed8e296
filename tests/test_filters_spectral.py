"""The filters in ``llvm_ad_spectral`` (docs/maths.md §10): every segment of a pool carries the pool's
wavelengths, and the images agree with a spectral ``path`` channel by channel.

There is no stored spectral reference: ``path`` renders one here per scene (cached for the module), at
``REF_SPP``. The filters render at a fixed kernel (side 0.1, ``alpha`` 1), as in
tests/test_filters_vs_references.py, and are judged by the same two numbers, per channel (R, G, B): the mean
ratio and the 1%-trimmed relMSE against the reference, over two 32-spp images.

All segments of a pool share one wavelength sample, so each pool's image is tinted as a whole (segment_mvf,
Cornell 16x16, 4-spp pools: the R, G and B image means have standard deviations of 23%, 15% and 60% over 256
pools, and their averages are within one standard error of the reference's). Independent pools would need
thousands of them to pin the means to 2-3%. The test therefore *stratifies* its pools' wavelength samples:
each image is a sum of calls of one pool each (4 spp, the default pool at 32x32), with seeds picked so that
their wavelength samples fall one in each of ``STRATA`` equal strata of ``frac(4 u)`` (the four wavelengths
of a lane are the shifts ``u + k/4``, so that is what they depend on). Stratified sampling with one sample per
stratum of equal weight is unbiased, so the filters must still agree with the reference, with the tint
mostly gone.
"""

from __future__ import annotations

import functools

import mitsuba as mi
import numpy as np
import pytest
from conftest import SCENES

from segmitsuba.population import LIGHT
from segmitsuba.schedule import pass_seed

RES, KERNEL, POOL_SPP, STRATA, REF_SPP = 32, 0.1, 4, 16, 4096
FILTERS = ("segment_mvf", "segment_pf", "segment_bdf")


def load(name: str, res: int = RES) -> mi.Scene:
    return mi.load_file(str(SCENES / f"{name}.xml"), res=res)


def relmse(img: np.ndarray, ref: np.ndarray, trim: float = 0.0) -> float:
    """As tests/test_filters_vs_references.py: ``trim`` drops that fraction of the largest errors."""
    err = np.sort(((img - ref) ** 2 / (ref**2 + 1e-2)).ravel())
    return float(np.mean(err[: len(err) - int(trim * len(err))]))


@functools.lru_cache
def reference(name: str) -> np.ndarray:
    """Spectral ``path`` (max_depth 8, as the stored RGB references) at ``REF_SPP``: every lane draws its own
    wavelengths, so its tint averages over all of its samples."""
    mi.set_variant("llvm_ad_spectral")
    integrator = mi.load_dict({"type": "path", "max_depth": 8})
    return np.array(mi.render(load(name), integrator=integrator, spp=REF_SPP, seed=12345), dtype=np.float64)[..., :3]


def stratified_seeds(strata: int, start: int = 0) -> list[int]:
    """One call seed per stratum ``j``: the first seed from ``start`` whose pool's wavelength sample ``u`` has
    ``floor(strata * frac(4 u)) == j``."""
    from segmitsuba.integrators.filtering import pool_wavelength_sample  # needs a variant

    seeds: list[int | None] = [None] * strata
    seed = start
    while None in seeds:
        j = int(strata * ((4 * pool_wavelength_sample(seed)) % 1.0))
        if seeds[j] is None:
            seeds[j] = seed
        seed += 1
    return seeds


@functools.lru_cache
def stratified_pools(method: str, name: str, variant: str = "llvm_ad_spectral") -> np.ndarray:
    """``STRATA`` images of one pool each (POOL_SPP), fixed kernel, seeds from :func:`stratified_seeds`."""
    mi.set_variant(variant)
    scene = load(name)
    props = {"type": method, "kernel_size": KERNEL, "alpha": 1.0, "spp_per_pass": POOL_SPP}
    return np.stack([np.array(mi.render(scene, integrator=mi.load_dict(props), spp=POOL_SPP, seed=s),
                              dtype=np.float64)[..., :3] for s in stratified_seeds(STRATA)])


def images(method: str, name: str, variant: str = "llvm_ad_spectral") -> list[np.ndarray]:
    """Two images of STRATA/2 pools (32 spp) each, every one stratified over every other stratum."""
    pools = stratified_pools(method, name, variant)
    return [pools[0::2].mean(axis=0), pools[1::2].mean(axis=0)]


#: (method, scene, mean-ratio tolerance per channel, 1%-trimmed relMSE bound per channel). Measured (R / G / B
#: mean ratio; relMSE): bdf cornell 0.967 / 0.965 / 0.968, 0.0054 / 0.0041 / 0.0030; bdf emitter_point
#: 0.997 / 1.001 / 0.994, 0.0036 / 0.0028 / 0.0044; mvf cornell 0.975 / 0.979 / 0.981, 0.022 / 0.016 / 0.011;
#: pf emitter_point 0.992 / 0.997 / 0.993, 0.0040 / 0.0031 / 0.0048. Left out for time: bdf emitter_area
#: 0.993 / 0.996 / 0.988, 0.0012 / 0.0011 / 0.0020; bdf glossy_occluded 1.013 / 1.014 / 1.005, 0.0032 /
#: 0.0029 / 0.0036 (49 s). The mean tolerances are the RGB test's (mvf, which that test does not hold to a
#: reference, takes Cornell's), except bdf on Cornell: with these seeds the RGB filter itself comes out
#: 0.967 / 0.965 / 0.963 of the stored RGB reference (test_spectral_cornell_tracks_rgb_on_the_same_seeds).
#: The relMSE bounds leave ~2x headroom.
CASES = [
    ("segment_bdf", "cornell", 0.04, 0.011),
    ("segment_bdf", "emitter_point", 0.02, 0.009),
    ("segment_mvf", "cornell", 0.03, 0.045),
    ("segment_pf", "emitter_point", 0.02, 0.01),
]


@pytest.mark.parametrize("method, name, tol_mean, tol_error", CASES)
def test_spectral_filter_agrees_with_spectral_path_per_channel(method, name, tol_mean, tol_error):
    ref = reference(name)
    imgs = images(method, name)
    assert np.isfinite(imgs).all()
    ratios = [np.mean([img[..., c].mean() for img in imgs]) / ref[..., c].mean() for c in range(3)]
    errors = [np.mean([relmse(img[..., c], ref[..., c], trim=0.01) for img in imgs]) for c in range(3)]
    print(f"{method} {name}: mean ratio R/G/B " + " / ".join(f"{r:.4f}" for r in ratios)
          + ", relMSE " + " / ".join(f"{e:.4f}" for e in errors))
    for channel, ratio, error in zip("RGB", ratios, errors, strict=True):
        assert abs(ratio - 1) < tol_mean, f"{method} {name} {channel}: mean ratio {ratio:.4f}"
        assert error < tol_error, f"{method} {name} {channel}: relMSE {error:.4f}"


def test_spectral_cornell_tracks_rgb_on_the_same_seeds():
    """The spectral pools use the random numbers of the RGB pools of the same seeds for everything but the
    wavelengths, so the kernel's and the pools' own errors are shared: per channel, the spectral ratio to
    spectral ``path`` follows the RGB filter's ratio to the stored RGB reference (measured: within 0.005 on
    these seeds, within 0.015 in blue on two other seed sets, the residual tint of 16 stratified pools)."""
    from segmitsuba.references import load_reference

    spectral = images("segment_bdf", "cornell")
    rgb = images("segment_bdf", "cornell", "llvm_ad_rgb")
    ref_spectral = reference("cornell")
    ref_rgb, _ = load_reference("cornell", res=RES, max_depth=8)
    for c, channel in enumerate("RGB"):
        a = np.mean([img[..., c].mean() for img in spectral]) / ref_spectral[..., c].mean()
        b = np.mean([img[..., c].mean() for img in rgb]) / ref_rgb[..., c].mean()
        print(f"cornell {channel}: spectral {a:.4f}, RGB {b:.4f}")
        assert abs(a - b) < 0.02, f"{channel}: spectral {a:.4f} against RGB {b:.4f}"


@pytest.mark.parametrize("method", FILTERS)
def test_every_segment_of_a_pool_carries_the_pools_wavelengths(method):
    """Camera and light records, escapes included, carry the wavelengths that ``sensor.sample_ray`` makes of
    the pool's one wavelength sample; another pool seed gives other wavelengths."""
    mi.set_variant("llvm_ad_spectral")
    from segmitsuba.integrators.filtering import pool_wavelength_sample  # needs a variant

    scene = load("cornell", res=8)
    sensor = scene.sensors()[0]
    integrator = mi.load_dict({"type": method})
    seen = []
    for seed in (3, 4):
        pool, paths, n_light = integrator.sample_pool(scene, sensor, 2, seed)
        ray, weight = sensor.sample_ray(0.0, pool_wavelength_sample(seed), mi.Point2f(0.5), mi.Point2f(0.5))
        expected = np.array(ray.wavelengths).reshape(-1, 1)
        assert np.array_equal(np.array(paths.wavelengths), np.broadcast_to(expected, (4, 8 * 8 * 2)))
        assert np.allclose(np.array(paths.sensor_weight), np.array(weight).reshape(-1, 1))
        assert np.array_equal(np.array(pool.surf.wavelengths), np.broadcast_to(expected, (4, pool.size)))
        assert (np.array(pool.kind) == LIGHT).any() == (method != "segment_mvf")
        seen.append(expected)
    assert not np.array_equal(*seen)


def test_pool_wavelength_samples_are_uniform():
    """One uniform number per pool seed, from a hash: spread over [0, 1) (the estimator is unbiased only if
    they are uniform), and the pools of a call get distinct ones."""
    from segmitsuba.integrators.filtering import pool_wavelength_sample  # (the variant of conftest)

    u = np.array([pool_wavelength_sample(s) for s in range(20000)])
    assert (u >= 0).all() and (u < 1).all()
    counts = np.histogram(u, bins=20, range=(0, 1))[0]
    assert np.all(np.abs(counts - 1000) < 5 * np.sqrt(1000)), counts
    pools = [pool_wavelength_sample(pass_seed(0, i)) for i in range(256)]  # the pools of one call of seed 0
    assert len(set(pools)) == len(pools)
