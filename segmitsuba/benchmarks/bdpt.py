"""Segment BDPT vs segment path tracing (``python -m segmitsuba.benchmarks.bdpt``).

Per scene (default: the caustic scene, and the delta caustic that path tracing cannot render), each method
renders at spp0, 2 spp0, ... until its time cap is spent (warm: one compile render first; every render closed
with ``dr.sync_thread()``). Each render gives (seconds, relMSE against the stored reference). Reported:

* **equal samples**: relMSE at the largest spp both methods reached (what bridges buy per sample);
* **equal time**: relMSE interpolated log-log at a common time T (the shorter curve's last time);
* **efficiency** 1 / (relMSE x seconds) at equal time, as a ratio segment_bdpt / segment_pt (> 1: BDPT wins).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import drjit as dr  # importing this module imported `segmitsuba` first, which set up libLLVM
import mitsuba as mi

from segmitsuba.references import DEFAULT_RES, scene_file, scene_stem

from .filtering import Curve, _curve, _fmt_s, _loglog, _reference

METHODS = ("segment_pt", "segment_bdpt")
DEFAULT_SCENES = "caustic,delta_caustic_point"


def _at_spp(curve: Curve, spp: int) -> tuple[float, float]:
    i = curve.spp.index(spp)
    return curve.seconds[i], curve.error[i]


def _scene_part(a: argparse.Namespace, stem: str) -> list[str]:
    scene: Any = mi.load_file(str(scene_file(stem)), res=a.res)
    ref, note = _reference(stem, scene, a.res, a.max_depth, a.ref_spp)
    curves = {m: _curve(scene, m, ref, a.max_depth, a.cap, a.spp0, a.max_spp) for m in METHODS}
    pt, bd = curves["segment_pt"], curves["segment_bdpt"]
    lines = ["", f"[{stem}] {a.res}x{a.res}, max_depth {a.max_depth}, cap {a.cap:g} s/method, reference: {note}"]
    for m, c in curves.items():
        pts = "  ".join(f"{n}:{_fmt_s(s)},{e:.2e}" for n, s, e in zip(c.spp, c.seconds, c.error, strict=True))
        lines.append(f"  {m:<13} {pts}")
    spp = max(set(pt.spp) & set(bd.spp))
    (t_pt, e_pt), (t_bd, e_bd) = _at_spp(pt, spp), _at_spp(bd, spp)
    lines.append(f"  equal samples ({spp} spp): relMSE segment_pt {e_pt:.3e} ({_fmt_s(t_pt)}), segment_bdpt "
                 f"{e_bd:.3e} ({_fmt_s(t_bd)}): BDPT error x{e_bd / e_pt:.3g} per sample, time x{t_bd / t_pt:.3g}")
    t = min(pt.seconds[-1], bd.seconds[-1])
    (ept, xpt), (ebd, xbd) = _loglog(pt.seconds, pt.error, t), _loglog(bd.seconds, bd.error, t)
    star = "*" if xpt or xbd else ""
    lines.append(f"  equal time (T = {_fmt_s(t)}): relMSE segment_pt {ept:.3e}, segment_bdpt {ebd:.3e}{star}; "
                 f"efficiency segment_bdpt / segment_pt = {ept / ebd:.3g}{star}")
    return lines


def run(args: list[str] | None = None) -> str:
    """Run the benchmark and return its table (``main`` prints it)."""
    ap = argparse.ArgumentParser(prog="segmitsuba.benchmarks.bdpt", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=DEFAULT_SCENES, help=f"comma-separated scenes (default {DEFAULT_SCENES})")
    ap.add_argument("--res", type=int, default=DEFAULT_RES, help="resolution (stored references at 32)")
    ap.add_argument("--cap", type=float, default=8.0, help="seconds of timed renders per method")
    ap.add_argument("--spp0", type=int, default=4, help="first spp of each curve (doubled after each render)")
    ap.add_argument("--max-spp", type=int, default=1 << 14, help="largest spp of a curve")
    ap.add_argument("--ref-spp", type=int, default=4096, help="spp of a path reference rendered here (res != 32)")
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="smoke run: caustic only, 1.5 s cap")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    a = ap.parse_args(args)
    if a.quick:
        a.scenes, a.cap = "caustic", min(a.cap, 1.5)

    mi.set_variant(a.variant)
    t0 = time.perf_counter()
    lines = [f"bdpt benchmark: {dr.thread_count()} threads, LLVM "
             f"{'.'.join(str(v) for v in dr.detail.llvm_version())}, variant {mi.variant()}"
             + (" (quick)" if a.quick else "")]
    for stem in (scene_stem(s) for s in a.scenes.split(",") if s):
        lines += _scene_part(a, stem)
    lines += ["", f"total {time.perf_counter() - t0:.0f} s"]
    return "\n".join(lines)


def main() -> None:
    print(run())


if __name__ == "__main__":
    main()
