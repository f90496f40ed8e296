"""Image metrics (segmitsuba.metrics): zero for identical images, scaling, trimming, FLIP range, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from segmitsuba import metrics


@pytest.fixture
def pair():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.05, 2.0, size=(24, 20, 3))
    img = np.maximum(ref * (1 + 0.2 * rng.standard_normal(ref.shape)), 0)
    return img, ref


@pytest.mark.parametrize("name", list(metrics.METRICS))
def test_zero_for_identical_images(pair, name):
    _, ref = pair
    assert metrics.METRICS[name](ref, ref.copy()) == 0.0


def test_relmse_and_mse_definitions(pair):
    img, ref = pair
    assert metrics.relmse(img, ref) == pytest.approx(np.mean((img - ref) ** 2 / (ref**2 + 1e-2)))
    assert metrics.relmse(img, ref, eps=0.5) == pytest.approx(np.mean((img - ref) ** 2 / (ref**2 + 0.5)))
    assert metrics.mse(img, ref) == pytest.approx(np.mean((img - ref) ** 2))
    # agrees with the references module's definition
    from segmitsuba.references import relmse as ref_relmse

    assert metrics.relmse(img, ref) == pytest.approx(ref_relmse(img, ref, ref=ref))


def test_scale_behaviour(pair):
    img, ref = pair
    d = img - ref
    # error twice as large: 4x the (rel)MSE
    assert metrics.mse(ref + 2 * d, ref) == pytest.approx(4 * metrics.mse(img, ref))
    assert metrics.relmse(ref + 2 * d, ref) == pytest.approx(4 * metrics.relmse(img, ref))
    # scaling both images: MSE by s^2; relMSE nearly scale-free for bright images (eps << ref^2)
    assert metrics.mse(10 * img, 10 * ref) == pytest.approx(100 * metrics.mse(img, ref))
    bright = metrics.relmse(100 * img, 100 * ref)
    assert bright == pytest.approx(metrics.relmse(1000 * img, 1000 * ref), rel=1e-3)


def test_trimmed_is_robust_and_never_larger(pair):
    img, ref = pair
    assert metrics.relmse_trimmed(img, ref) <= metrics.relmse(img, ref)
    assert metrics.relmse_trimmed(img, ref, trim=0.0) == pytest.approx(metrics.relmse(img, ref))
    spiky = img.copy()
    spiky[3, 4, 1] = 1e4  # one firefly
    assert metrics.relmse(spiky, ref) > 100 * metrics.relmse(img, ref)
    assert metrics.relmse_trimmed(spiky, ref) <= metrics.relmse(img, ref) * 1.01
    # a trim that drops nothing (fewer than 1/trim values) is the plain relMSE
    assert metrics.relmse_trimmed(img[:2, :2], ref[:2, :2]) == pytest.approx(metrics.relmse(img[:2, :2], ref[:2, :2]))


def test_flip_range_and_ordering(pair):
    img, ref = pair
    small = metrics.flip(ref + 0.1 * (img - ref), ref)
    large = metrics.flip(img, ref)
    assert 0.0 < small < large <= 1.0
    assert 0.0 <= metrics.flip(np.zeros_like(ref), ref) <= 1.0
    grey = ref[..., 0]
    assert 0.0 < metrics.flip(img[..., 0], grey) <= 1.0
    # a black reference has no HDR exposure range: LDR fallback, no crash
    black = np.zeros_like(ref)
    assert metrics.flip(black, black) == 0.0
    assert 0.0 < metrics.flip(img, black) <= 1.0
    # small negative values (unbiased estimators) are clamped
    assert 0.0 <= metrics.flip(img - 0.01, ref) <= 1.0


@pytest.mark.parametrize("name", list(metrics.METRICS))
def test_bad_input(pair, name):
    img, ref = pair
    fn = metrics.METRICS[name]
    with pytest.raises(ValueError, match="shape"):
        fn(img[:, :-1], ref)
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        fn(bad, ref)
    with pytest.raises(ValueError, match="non-finite"):
        fn(img, np.where(ref > 1, np.inf, ref))


def test_bad_parameters(pair):
    img, ref = pair
    with pytest.raises(ValueError, match="trim"):
        metrics.relmse_trimmed(img, ref, trim=1.0)
    with pytest.raises(ValueError, match="eps"):
        metrics.relmse(img, ref, eps=0)
