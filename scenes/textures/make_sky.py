"""Generate scenes/textures/sky.exr: a tiny 64x32 latitude-longitude sky for envmap scenes.

Sky gradient (bluish zenith -> whitish horizon), a dim brown ground below the
horizon, and a bright 2x2-pixel "sun" about 40 degrees above the horizon.
Run from anywhere:  python scenes/textures/make_sky.py
"""
import os

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

W, H = 64, 32


def make_sky() -> np.ndarray:
    # Row i covers polar angle theta in [i, i+1] * pi / H, measured from +Y (up).
    theta = (np.arange(H) + 0.5) / H * np.pi
    elev = np.pi / 2 - theta  # elevation above the horizon
    t = np.clip(np.sin(elev), 0.0, 1.0)[:, None]  # 0 at horizon, 1 at zenith
    zenith = np.array([0.15, 0.3, 0.8])
    horizon = np.array([0.8, 0.85, 0.9])
    sky = horizon * (1 - t) + zenith * t
    ground = np.array([0.08, 0.06, 0.04])
    col = np.where((elev > 0)[:, None], sky, ground)
    img = np.repeat(col[:, None, :], W, axis=1).astype(np.float32)
    # Sun: 2x2 pixels, rows 7-8 (elevation ~ 40 deg), columns 40-41.
    img[7:9, 40:42] = np.array([150.0, 140.0, 120.0], dtype=np.float32)
    return img


if __name__ == "__main__":
    out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "sky.exr")
    mi.Bitmap(make_sky()).write(out)
    print("wrote", out, os.path.getsize(out), "bytes")
