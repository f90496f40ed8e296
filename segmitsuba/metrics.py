"""Image error metrics against a reference: numpy arrays in, a float out.

    from segmitsuba.metrics import relmse, relmse_trimmed, mse, flip

    relmse(img, ref)            # mean((img - ref)^2 / (ref^2 + 1e-2)) over pixels and channels
    relmse_trimmed(img, ref)    # the same without the largest 0.1% of the per-value errors (fireflies)
    mse(img, ref)               # mean((img - ref)^2)
    flip(img, ref)              # mean HDR-FLIP (NVIDIA's perceptual error, in [0, 1])

Images are H x W (grey) or H x W x C; both must have the same shape and be finite (a NaN or inf is a
ValueError: it would poison a mean silently). ``flip`` uses the RGB channels (grey is repeated to RGB).

**FLIP.** :func:`flip` computes *HDR-FLIP* with the ``flip-evaluator`` package (``pip install flip-evaluator``):
both images are taken as linear sRGB radiance, negative values are clamped to 0 (HDR-FLIP needs nonnegative
input; unbiased estimators can produce small negatives), and FLIP chooses the exposure range from the
reference (ACES tone mapper, 67 pixels per degree). The one exception: a reference that is black everywhere has
no exposure range (the package aborts the process on it), so then LDR-FLIP of the images clamped to [0, 1]
is returned (0 if the test image is black too). :data:`FLIP_MODE` names this convention.
"""

from __future__ import annotations

import math

import numpy as np

#: the regularizer of the relMSE denominator (the same as ``segmitsuba.references``)
RELMSE_EPS = 1e-2
#: how :func:`flip` computes FLIP (see the module docstring)
FLIP_MODE = "HDR-FLIP (flip-evaluator, linear sRGB, negatives clamped to 0; LDR-FLIP of [0,1]-clamped images " \
            "if the reference is all black)"


def _pair(img: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(img, dtype=np.float64)
    b = np.asarray(ref, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"image and reference differ in shape: {a.shape} vs {b.shape}")
    if a.size == 0:
        raise ValueError("empty images")
    if a.ndim not in (2, 3):
        raise ValueError(f"expected H x W or H x W x C images, got shape {a.shape}")
    for name, x in (("image", a), ("reference", b)):
        if not np.all(np.isfinite(x)):
            bad = int(np.count_nonzero(~np.isfinite(x)))
            raise ValueError(f"{name} has {bad} non-finite value{'s' if bad != 1 else ''} (NaN or inf)")
    return a, b


def relmse_values(img: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS) -> np.ndarray:
    """Per-value relative squared errors (img - ref)^2 / (ref^2 + eps), same shape as the images."""
    if not eps > 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    a, b = _pair(img, ref)
    return (a - b) ** 2 / (b**2 + eps)


def relmse(img: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS) -> float:
    """Relative MSE: mean((img - ref)^2 / (ref^2 + eps)) over pixels and channels."""
    return float(np.mean(relmse_values(img, ref, eps)))


def relmse_trimmed(img: np.ndarray, ref: np.ndarray, trim: float = 0.001, eps: float = RELMSE_EPS) -> float:
    """relMSE without the largest ``trim`` fraction (floor(trim * count) values) of the per-value errors: robust
    to a few outliers (fireflies). Never larger than :func:`relmse`; equal to it when nothing is dropped."""
    if not 0 <= trim < 1:
        raise ValueError(f"trim must be in [0, 1), got {trim}")
    values = relmse_values(img, ref, eps).ravel()
    drop = int(math.floor(trim * values.size))
    if drop == 0:
        return float(np.mean(values))
    kept = np.partition(values, values.size - drop - 1)[: values.size - drop]
    return float(np.mean(kept))


def mse(img: np.ndarray, ref: np.ndarray) -> float:
    """Mean squared error over pixels and channels."""
    a, b = _pair(img, ref)
    return float(np.mean((a - b) ** 2))


def _rgb32(x: np.ndarray) -> np.ndarray:
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[2] >= 3:
        x = x[..., :3]
    else:
        x = np.repeat(x[..., :1], 3, axis=2)
    return np.ascontiguousarray(x, dtype=np.float32)


def flip(img: np.ndarray, ref: np.ndarray) -> float:
    """Mean FLIP error in [0, 1] (0: identical); HDR-FLIP, see the module docstring (:data:`FLIP_MODE`)."""
    a, b = _pair(img, ref)
    try:
        import flip_evaluator
    except ImportError:
        raise ImportError("FLIP needs the flip-evaluator package: pip install flip-evaluator") from None
    test, reference = _rgb32(np.maximum(a, 0.0)), _rgb32(np.maximum(b, 0.0))
    if reference.max() <= 0.0:  # no exposure range: flip-evaluator would abort the process
        if test.max() <= 0.0:
            return 0.0
        _, value, _ = flip_evaluator.evaluate(np.clip(reference, 0, 1), np.clip(test, 0, 1), "LDR",
                                              inputsRGB=False, applyMagma=False)
    else:
        _, value, _ = flip_evaluator.evaluate(reference, test, "HDR", applyMagma=False)
    return float(min(max(value, 0.0), 1.0))


#: name -> function, in the order reports list them
METRICS = {"relmse": relmse, "relmse_trimmed": relmse_trimmed, "mse": mse, "flip": flip}
