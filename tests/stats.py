"""Statistical comparison of two unbiased renderers over independent seeds."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np


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
    """z-scores of the difference of means of two independent sample sets along axis 0."""
    se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
    diff = a.mean(axis=0) - b.mean(axis=0)
    # Tiles that are exactly zero in both (black background) have no variance: z = 0 if they agree.
    return np.where(se > 0, diff / np.where(se > 0, se, 1), np.where(diff == 0, 0.0, np.inf))


def compare(images_a: np.ndarray, images_b: np.ndarray, tiles: int = 4) -> ZResult:
    ma = images_a[..., :3].mean(axis=(1, 2, 3))
    mb = images_b[..., :3].mean(axis=(1, 2, 3))
    return ZResult(z_image=float(_z(ma, mb)), z_tiles=_z(tile_means(images_a, tiles), tile_means(images_b, tiles)),
                   mean_a=float(ma.mean()), mean_b=float(mb.mean()))
