"""Generate scenes/textures/checker_light.exr: a 3x3 HDR checkerboard used as the
radiance texture of the ceiling light in textured_bitmap.xml (same pattern and
colours as the procedural `checkerboard` light in textured.xml).

Run from anywhere:  python scenes/textures/make_checker.py
"""
import os

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

N = 3  # cells per side (checkerboard texture with to_uv scale 1.5 -> 3 cells)
COLOR0 = (5.0, 4.5, 3.8)
COLOR1 = (0.3, 0.5, 1.0)


def make_checker() -> np.ndarray:
    i, j = np.mgrid[0:N, 0:N]
    even = ((i + j) % 2 == 0)[..., None]
    return np.where(even, np.array(COLOR0), np.array(COLOR1)).astype(np.float32)


if __name__ == "__main__":
    out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "checker_light.exr")
    mi.Bitmap(make_checker()).write(out)
    print("wrote", out, os.path.getsize(out), "bytes")
