"""Statistical comparison of two unbiased renderers over independent seeds."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
import scipy.stats


def render_seeds(scene: mi.Scene, integrator: mi.Integrator, spp: int, seeds: range) -> np.ndarray:
    """Images (K, H, W, C) of independent renders, one per seed."""
    images = []
    for seed in seeds:
        img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        images.append(np.array(img, dtype=np.float64))
    dr.sync_thread()
    return np.stack(images)


def tile_means(images: np.ndarray, tiles: int) -> np.ndarray:
    """Per-render means over a tiles×tiles grid and the colour channels: (K, tiles*tiles)."""
    k, h, w, c = images.shape
    ys = np.array_split(np.arange(h), tiles)
    xs = np.array_split(np.arange(w), tiles)
    rgb = images[..., :3]
    out = [rgb[:, y][:, :, x].mean(axis=(1, 2, 3)) for y in ys for x in xs]
    return np.stack(out, axis=1)


@dataclass
class ZResult:
    z_image: float
    z_tiles: np.ndarray
    mean_a: float
    mean_b: float

    @property
    def max_abs(self) -> float:
        return float(max(abs(self.z_image), np.max(np.abs(self.z_tiles))))

    def __str__(self) -> str:
        return (f"means {self.mean_a:.5g} vs {self.mean_b:.5g}, z(image)={self.z_image:+.2f}, "
                f"max |z(tile)|={np.max(np.abs(self.z_tiles)):.2f}")


def _z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z-scores of the difference of means of two independent sample sets along axis 0.

    With few seeds the variance is itself estimated, so the statistic follows Student's t (Welch's degrees
    of freedom), not a normal law. It is reported as the normal z of the same two-sided p-value, so that a
    bound such as |z| < 4 keeps its usual meaning (p > 6e-5) whatever the number of seeds.
    """
    va, vb = a.var(axis=0, ddof=1) / len(a), b.var(axis=0, ddof=1) / len(b)
    se = np.sqrt(va + vb)
    diff = a.mean(axis=0) - b.mean(axis=0)
    safe = np.where(se > 0, se, 1)
    t = diff / safe
    dof = np.where(se > 0, (va + vb) ** 2 / np.where(se > 0, va**2 / (len(a) - 1) + vb**2 / (len(b) - 1), 1), 1)
    p = 2 * scipy.stats.t.sf(np.abs(t), np.maximum(dof, 1))
    z = np.sign(t) * scipy.stats.norm.isf(p / 2)
    # Tiles that are exactly zero in both (black background) have no variance: z = 0 if they agree.
    return np.where(se > 0, z, np.where(diff == 0, 0.0, np.inf))


def compare(images_a: np.ndarray, images_b: np.ndarray, tiles: int = 4) -> ZResult:
    ma = images_a[..., :3].mean(axis=(1, 2, 3))
    mb = images_b[..., :3].mean(axis=(1, 2, 3))
    return ZResult(z_image=float(_z(ma, mb)), z_tiles=_z(tile_means(images_a, tiles), tile_means(images_b, tiles)),
                   mean_a=float(ma.mean()), mean_b=float(mb.mean()))
