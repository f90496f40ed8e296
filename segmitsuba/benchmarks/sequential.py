"""Sequential-estimation integrators vs Mitsuba's (``python -m segmitsuba.benchmarks.sequential``).

``segment_pt`` is timed against Mitsuba's ``path`` and ``segment_lt`` against ``ptracer``, at equal spp
(light paths per pixel for the light tracers) and equal ``max_depth``, on one scene (the Cornell box by
default). Every time is warm: each integrator renders once to compile its kernels, then the best of ``R``
timed renders (each closed with ``dr.sync_thread()``, since launches are asynchronous) is reported. The image
means of each pair are printed as a check that both render the same thing.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import drjit as dr  # importing this module imported `segmitsuba` first, which set up libLLVM
import mitsuba as mi
import numpy as np

#: repository root (the parent of the package directory)
ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SCENE = "scenes/cornell.xml"
#: segment_pt may take at most this multiple of path's time
PT_TARGET = 1.5


def _scene_path(name: str) -> Path:
    """``name`` as given if it exists, else relative to the repository root."""
    p = Path(name)
    return p if p.exists() or p.is_absolute() else ROOT / p


def _time_render(scene: Any, name: str, max_depth: int, spp: int, reps: int) -> tuple[float, np.ndarray]:
    """Best warm time of ``reps`` renders with integrator ``name``, and the image of the warm-up render."""
    integrator = mi.load_dict({"type": name, "max_depth": max_depth})
    image = mi.render(scene, integrator=integrator, spp=spp, seed=0)  # warm-up: compile
    dr.eval(image)
    dr.sync_thread()
    best = float("inf")
    for i in range(reps):
        t0 = time.perf_counter()
        out = mi.render(scene, integrator=integrator, spp=spp, seed=i + 1)
        dr.eval(out)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    return best, np.asarray(image)


def _means(img: np.ndarray) -> str:
    rgb = img[..., :3].reshape(-1, 3).mean(axis=0)
    return f"mean {rgb.mean():.5f}  (RGB {rgb[0]:.4f} {rgb[1]:.4f} {rgb[2]:.4f})"


def run(args: list[str] | None = None) -> str:
    """Run the benchmark and return its table (``main`` prints it)."""
    ap = argparse.ArgumentParser(prog="segmitsuba.benchmarks.sequential", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=DEFAULT_SCENE,
                    help="scene file declaring `res` and `spp` defaults (relative paths: cwd, then repo root)")
    ap.add_argument("--res", type=int, default=256, help="image width and height")
    ap.add_argument("--spp", type=int, default=64, help="samples (light paths for the tracers) per pixel")
    ap.add_argument("--reps", type=int, default=3, help="timed renders per integrator (best is reported)")
    ap.add_argument("--max-depth", type=int, default=6)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    a = ap.parse_args(args)

    mi.set_variant(a.variant)
    scene_file = _scene_path(a.scene)
    scene = mi.load_file(str(scene_file), res=a.res, spp=a.spp)

    times: dict[str, float] = {}
    images: dict[str, np.ndarray] = {}
    for name in ("path", "segment_pt", "ptracer", "segment_lt"):
        times[name], images[name] = _time_render(scene, name, a.max_depth, a.spp, a.reps)

    ms = 1e3
    r_pt = times["segment_pt"] / times["path"]
    r_lt = times["segment_lt"] / times["ptracer"]
    verdict = "PASS" if r_pt <= PT_TARGET else "MISS"
    rows: list[tuple[str, str]] = [
        ("path", f"{times['path'] * ms:9.1f} ms   {_means(images['path'])}"),
        ("segment_pt", f"{times['segment_pt'] * ms:9.1f} ms   {_means(images['segment_pt'])}"),
        ("  ratio segment_pt / path", f"{r_pt:9.2f} x    (target <= {PT_TARGET} x: {verdict})"),
        ("ptracer", f"{times['ptracer'] * ms:9.1f} ms   {_means(images['ptracer'])}"),
        ("segment_lt", f"{times['segment_lt'] * ms:9.1f} ms   {_means(images['segment_lt'])}"),
        ("  ratio segment_lt / ptracer", f"{r_lt:9.2f} x"),
    ]
    try:
        scene_name = str(scene_file.relative_to(ROOT))
    except ValueError:
        scene_name = str(scene_file)
    width = max(len(k) for k, _ in rows)
    lines = [
        f"sequential benchmark: {scene_name}, {a.res}x{a.res}, {a.spp} spp, max_depth {a.max_depth}, "
        f"best of {a.reps} warm renders",
        f"  machine: {dr.thread_count()} threads, LLVM {dr.detail.llvm_version()}, variant {mi.variant()}",
    ]
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    return "\n".join(lines)


def main() -> None:
    print(run())


if __name__ == "__main__":
    main()
