"""The demo picture (``make demo``, ``python -m segmitsuba.demo``): Mitsuba's ``path`` and ``segment_bdf`` for
the same render time on the caustic scene at 256x256, against its stored converged reference.

Each method renders in passes for ``--time`` seconds (default 20; JIT compilation excluded, as in
:func:`segmitsuba.compare.run_method`). Writes ``demo.png`` (the two images side by side with the reference,
each labelled with its method, render time, spp and relMSE against the reference) and ``demo_<method>.exr``
(float32, with the render metadata) to ``--out`` (default ``out/``). About a minute on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

DEFAULT_TIME = 20.0
DEFAULT_SCENE = "caustic"
DEFAULT_RES = 256
METHODS = ("path", "segment_bdf")


def labelled_images(panels: Sequence[tuple[np.ndarray, str]], path: Path, exposure: float = 0.0) -> None:
    """Write the images (linear RGB, same size) side by side as one PNG at their own pixel size, each with its
    label written on it (bottom left, white on a dark box)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .imageio import to_srgb8

    h, w = panels[0][0].shape[:2]
    gap = 4
    dpi = 100
    fig = plt.figure(figsize=((len(panels) * w + (len(panels) - 1) * gap) / dpi, h / dpi), dpi=dpi)
    fig.patch.set_facecolor("white")
    for k, (image, label) in enumerate(panels):
        ax = fig.add_axes(((k * (w + gap)) / (len(panels) * w + (len(panels) - 1) * gap), 0.0,
                           w / (len(panels) * w + (len(panels) - 1) * gap), 1.0))
        ax.imshow(to_srgb8(image, exposure), interpolation="nearest")
        ax.set_axis_off()
        ax.text(0.025, 0.025, label, transform=ax.transAxes, va="bottom", ha="left", color="white", fontsize=7.5,
                family="monospace", bbox={"facecolor": "black", "alpha": 0.6, "edgecolor": "none", "pad": 2.5})
    fig.savefig(path, dpi=dpi, facecolor=fig.get_facecolor())
    plt.close(fig)


def demo(out: Path = Path("out"), time_budget: float = DEFAULT_TIME, scene_name: str = DEFAULT_SCENE,
         res: int = DEFAULT_RES, methods: Sequence[str] = METHODS, seed: int = 0,
         say: Callable[[str], None] | None = None) -> dict[str, dict[str, float]]:
    """Render ``scene_name`` at ``res`` with each method for ``time_budget`` seconds against its stored
    reference, write the picture and the EXRs to ``out`` and return each method's final metrics (time, spp,
    relmse, ...). Sets the ``llvm_ad_rgb`` variant if none is set."""
    import mitsuba as mi

    from . import __version__
    from .benchmarks.equal_time import reference_for
    from .compare import run_method
    from .imageio import write_exr
    from .references import DEFAULT_MAX_DEPTH, scene_file

    if not mi.variant():
        mi.set_variant("llvm_ad_rgb")
    ref, info = reference_for(scene_name, res)
    scene = mi.load_file(str(scene_file(scene_name)), res=res)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    panels, finals = [], {}
    for method in methods:
        if say is not None:
            say(f"{method}: {time_budget:g} s on {scene_name} {res}x{res}")
        run = run_method(scene, method, ref, time_budget, {"max_depth": DEFAULT_MAX_DEPTH}, seed, True,
                         flip_every=False)
        assert run.image is not None
        f = run.final
        finals[method] = f
        write_exr(out / f"demo_{method}.exr", run.image, ["R", "G", "B"],
                  {"software": f"segmitsuba {__version__}", "scene": f"scenes/{scene_name}.xml", "integrator": method,
                   "max_depth": DEFAULT_MAX_DEPTH, "spp": int(f["spp"]), "render_time": float(f["time"]),
                   "relmse": float(f["relmse"]), "reference": info["path"]})
        panels.append((run.image, f"{method}\n{f['time']:.1f} s, {int(f['spp'])} spp\nrelMSE {f['relmse']:.2e}"))
        if say is not None:
            say(f"  {method}: {f['time']:.1f} s, {int(f['spp'])} spp, relMSE {f['relmse']:.3e}")
    panels.append((ref, f"reference\n{info['integrator']}, {info['spp']} spp\n"
                        f"(own relMSE ~{info['expected_relmse']:.0e})"))
    labelled_images(panels, out / "demo.png")
    return finals


def main(argv: list[str] | None = None) -> int:
    """``python -m segmitsuba.demo [--out DIR] [--time SECONDS]``."""
    import segmitsuba  # noqa: F401  (libLLVM set-up and plugins, also when run as a script)

    ap = argparse.ArgumentParser(prog="python -m segmitsuba.demo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("out"), help="output folder (default out/)")
    ap.add_argument("--time", type=float, default=DEFAULT_TIME, help=f"seconds per method (default {DEFAULT_TIME:g})")
    a = ap.parse_args(argv)
    if not a.time > 0:
        ap.error("--time must be > 0")
    t0 = time.perf_counter()
    demo(a.out, a.time, say=lambda m: print(m, flush=True))
    print(f"wrote {a.out / 'demo.png'} and {', '.join(str(a.out / f'demo_{m}.exr') for m in METHODS)} "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
