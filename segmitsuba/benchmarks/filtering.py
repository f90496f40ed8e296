"""Filtering integrators vs Mitsuba's ``path`` (``python -m segmitsuba.benchmarks.filtering``).

Three parts, every time warm (each integrator renders once to compile its kernels; timed renders are
closed with ``dr.sync_thread()``, since launches are asynchronous):

1. **Time to error.** Per scene, each method (``path``, ``segment_pt``, ``segment_mvf``, ``segment_pf``,
   ``segment_bdf``; ``max_depth`` 8 for all) renders at 4, 8, 16, ... spp until its time cap (the sum of its
   timed renders) is spent; each render gives (time, relMSE vs the reference), relMSE =
   mean((img - ref)^2 / (ref^2 + 1e-2)). At a common time T (the time of path's ``--at-spp`` point, raised
   to the first point of the slowest method, lowered to the last point of the shortest curve) each method's
   relMSE is interpolated log-log; the time-to-error ratio is (time path needs to reach that relMSE) / T,
   so > 1 means faster than path. Values marked ``*`` are extrapolated (log-log slope of the nearest points).
   At res 32 the stored references are used (``segmitsuba.references``); at other resolutions ``path``
   renders one with ``--ref-spp`` spp.
2. **Per-pass breakdown** of ``segment_bdf`` (one pass of ``spp_per_pass`` spp): trace, system (grid,
   denominators, edge weights), solve, segments, edges, and the filtering overhead (system + solve) / trace;
   the trace's time per pool segment against ``path``'s time per camera segment of the pool (``path`` walks
   camera paths of the same distribution, with its emitter samples) at the same spp, fastest against fastest,
   and the median over the passes of each pass's ratio to ``path`` rendered right after it.
3. **Pass time vs population size**: one ``segment_bdf`` pass at spp_per_pass 1, 2, 4, 8 with a fixed kernel
   size (radius: the one the integrator derives for the scene at spp 1), and its time per segment.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass, field
from typing import Any

import drjit as dr  # importing this module imported `segmitsuba` first, which set up libLLVM
import mitsuba as mi
import numpy as np

from segmitsuba.film import film_sample_count
from segmitsuba.references import (
    DEFAULT_RES,
    load_reference,
    relmse,
    scene_file,
    scene_stem,
)
from segmitsuba.rendering import render_passes

METHODS = ("path", "segment_pt", "segment_mvf", "segment_pf", "segment_bdf")
DEFAULT_SCENES = "caustic,cornell,glossy_occluded"
#: the filtering overhead (system + solve) / trace aimed at
OVERHEAD_TARGET = 2.0
#: the tracing cost per pool segment aimed at, relative to ``path``'s per camera segment
TRACE_TARGET = 1.5


@dataclass
class Curve:
    """A method's (spp, seconds, relMSE) points, in increasing spp."""

    method: str
    spp: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    error: list[float] = field(default_factory=list)


# --- helpers -----------------------------------------------------------------------------------------------


def _timed_render(scene: Any, integrator: Any, spp: int, seed: int) -> tuple[float, np.ndarray]:
    dr.sync_thread()
    t0 = time.perf_counter()
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    return seconds, np.asarray(image)[..., :3]


def _loglog(xs: list[float], ys: list[float], x: float) -> tuple[float, bool]:
    """y at x, linear in log-log between the points (xs increasing); beyond them, the slope of the nearest
    three points (least squares). Returns (y, extrapolated)."""
    lx, ly = np.log(np.asarray(xs, dtype=np.float64)), np.log(np.asarray(ys, dtype=np.float64))
    t = math.log(x)
    if len(lx) == 1:
        return float(ys[0] * xs[0] / x), True  # assume y ~ 1 / x
    if lx[0] <= t <= lx[-1]:
        return float(math.exp(np.interp(t, lx, ly))), False
    sel = slice(0, 3) if t < lx[0] else slice(-3, None)
    slope, icpt = np.polyfit(lx[sel], ly[sel], 1)
    return float(math.exp(icpt + slope * t)), True


def _time_to_error(curve: Curve, target: float) -> tuple[float, str]:
    """Seconds the (decreasing, but noisy) error curve needs to reach ``target``, and a mark: the first
    segment that crosses it, interpolated log-log (""); beyond the curve's end, its end slope (at most -0.25,
    else -1; "*"); already reached by the first point: that point's time, an upper bound ("<")."""
    lt = np.log(np.asarray(curve.seconds, dtype=np.float64))
    le = np.log(np.asarray(curve.error, dtype=np.float64))
    g = math.log(target)
    if le[0] <= g:
        return curve.seconds[0], "<" if le[0] < g else ""
    for i in range(1, len(lt)):
        if le[i] <= g:
            f = (g - le[i - 1]) / (le[i] - le[i - 1])
            return float(math.exp(lt[i - 1] + f * (lt[i] - lt[i - 1]))), ""
    slope = np.polyfit(lt[-3:], le[-3:], 1)[0] if len(lt) > 1 else -1.0
    slope = slope if slope < -0.25 else -1.0
    return float(math.exp(lt[-1] + (g - le[-1]) / slope)), "*"


def _integrator(name: str, max_depth: int, **props: Any) -> Any:
    return mi.load_dict({"type": name, "max_depth": max_depth, **props})


def _kernel(stats: dict[str, Any]) -> tuple[str, str, float]:
    """(kernel description, property that fixes its size, size) from ``last_stats``; the integrators
    report either ``radius`` or ``kernel`` + ``kernel_size``."""
    if "kernel_size" in stats:
        return f"{stats.get('kernel', '?')} kernel, size", "kernel_size", float(stats["kernel_size"])
    return "radius", "radius", float(stats["radius"])


def _fmt_s(seconds: float) -> str:
    return f"{seconds * 1e3:.0f} ms" if seconds < 1 else f"{seconds:.2f} s"


# --- part 1: time to error ---------------------------------------------------------------------------------


def _reference(stem: str, scene: Any, res: int, max_depth: int, ref_spp: int) -> tuple[np.ndarray, str]:
    if res == DEFAULT_RES and max_depth == 8:
        try:
            image, meta = load_reference(stem, res, max_depth)
            floor = meta.get("expected_relmse", meta.get("half_relmse", float("nan")))
            return image[..., :3], f"stored {meta.get('integrator', '?')} {meta.get('spp', '?')} spp, " \
                                   f"own relMSE ~{float(floor):.1e}"
        except FileNotFoundError:
            pass
    result = render_passes(scene, _integrator("path", max_depth), spp=ref_spp, seed=987654321, progress=False)
    return result.image[..., :3], f"path {ref_spp} spp rendered here ({result.seconds:.1f} s)"


def _curve(scene: Any, method: str, ref: np.ndarray, max_depth: int, cap: float, spp0: int, max_spp: int,
           until: tuple[float, float] | None = None) -> Curve:
    """Renders at spp0, 2 spp0, ... while the timed renders fit in ``cap`` seconds. With ``until`` =
    (seconds, relMSE), also go on (up to 4 cap) until a render takes that long and reaches that relMSE."""
    integrator = _integrator(method, max_depth)
    _timed_render(scene, integrator, spp0, seed=0)  # warm-up: compile
    curve = Curve(method)
    spp, spent, seed = spp0, 0.0, 1
    while spp <= max_spp:
        seconds, image = _timed_render(scene, integrator, spp, seed)
        curve.spp.append(spp)
        curve.seconds.append(seconds)
        curve.error.append(relmse(image, ref, ref=ref))
        spent += seconds
        seed += 1
        spp *= 2
        more = until is not None and (seconds < until[0] or min(curve.error) > until[1])
        if spent + 2 * seconds > (4 * cap if more else cap):  # the next render takes about twice as long
            break
    return curve


def _time_to_error_part(a: argparse.Namespace, scenes: list[str]) -> tuple[list[str], dict[str, dict[str, str]]]:
    lines: list[str] = []
    summary: dict[str, dict[str, str]] = {m: {} for m in a.methods}
    for stem in scenes:
        scene = mi.load_file(str(scene_file(stem)), res=a.res)
        ref, ref_note = _reference(stem, scene, a.res, a.max_depth, a.ref_spp)
        others = {m: _curve(scene, m, ref, a.max_depth, a.cap, a.spp0, a.max_spp) for m in a.methods[1:]}
        # path last, from 1 spp, and on until it covers the others' times and errors (so that the ratios
        # interpolate rather than extrapolate)
        until = (max((c.seconds[-1] for c in others.values()), default=0.0),
                 min((min(c.error) for c in others.values()), default=1.0))
        path = _curve(scene, "path", ref, a.max_depth, a.cap, 1, a.max_spp, until)
        curves = {"path": path, **others}
        # common time: path's --at-spp point, at least every curve's first point, at most the others' last
        at = [s for n, s in zip(path.spp, path.seconds, strict=True) if n >= a.at_spp]
        t_common = at[0] if at else path.seconds[-1]
        t_common = max(t_common, *(c.seconds[0] for c in curves.values()))
        t_common = min([t_common, *(c.seconds[-1] for c in others.values())])
        lines.append("")
        lines.append(f"[{stem}] {a.res}x{a.res}, max_depth {a.max_depth}, cap {a.cap:g} s/method, "
                     f"reference: {ref_note}")
        lines.append(f"  equal time T = {_fmt_s(t_common)}")
        head = f"  {'method':<12} {'spp':>11} {'time':>17} {'relMSE':>17} {'relMSE@T':>10} " \
               f"{'path t(err)':>11} {'ratio':>7}"
        lines.append(head)
        lines.append("  " + "-" * (len(head) - 2))
        for m, c in curves.items():
            e_t, ex = _loglog(c.seconds, c.error, t_common)
            t_path, mark = _time_to_error(path, e_t)
            ratio = t_path / t_common
            star = "<" if mark == "<" else ("*" if ex or mark else " ")
            summary[m][stem] = f"{'<' if mark == '<' else ''}{ratio:.3g}{'*' if star == '*' else ''}"
            lines.append(
                f"  {m:<12} {c.spp[0]:>5}-{c.spp[-1]:<5} {_fmt_s(c.seconds[0]):>8}-{_fmt_s(c.seconds[-1]):<8} "
                f"{c.error[0]:.2e}-{c.error[-1]:.2e} {e_t:>9.2e}{'*' if ex else ' '} "
                f"{_fmt_s(t_path):>10}{mark or ' '} {summary[m][stem]:>7}")
        lines.append("  curves (spp: time, relMSE):")
        for m, c in curves.items():
            pts = "  ".join(f"{n}:{_fmt_s(s)},{e:.2e}" for n, s, e in zip(c.spp, c.seconds, c.error, strict=True))
            lines.append(f"    {m:<12} {pts}")
    return lines, summary


# --- parts 2 and 3: segment_bdf passes ---------------------------------------------------------------------


def _bdf_pass(scene: Any, integrator: Any, spp: int, reps: int, alongside: Any = None) -> dict[str, float]:
    """``last_stats`` of ``reps`` one-pass renders (after a warm-up), each time the minimum over the reps (the
    machine may be shared), and the render's wall time as ``wall``. ``alongside``: another integrator rendered
    after each of them, its fastest time as ``time_alongside``, and ``trace_per_segment_ratio``, the median
    over the reps of each pass's trace time per pool segment over the rendering's time per camera segment of
    the pool: pairs rendered back to back see the same speed of the machine, whose drift over a run the fastest
    of each alone does not cancel."""
    _timed_render(scene, integrator, spp, seed=0)
    if alongside is not None:
        _timed_render(scene, alongside, spp, seed=0)
    out: dict[str, float] = {}
    ratios = []
    for i in range(reps):
        seconds, _ = _timed_render(scene, integrator, spp, seed=i + 1)
        stats = dict(integrator.last_stats, wall=seconds)
        if alongside is not None:
            stats["time_alongside"] = _timed_render(scene, alongside, spp, seed=i + 1)[0]
            ratios.append((stats["time_trace"] / max(1, stats["segments"]))
                          / (stats["time_alongside"] / max(1, stats["camera_segments"])))
        for key, value in stats.items():
            out[key] = min(out.get(key, value), value) if key.startswith(("time", "wall")) else value
    if ratios:
        out["trace_per_segment_ratio"] = statistics.median(ratios)
    return out


def _breakdown_part(a: argparse.Namespace) -> list[str]:
    scene = mi.load_file(str(scene_file(a.pass_scene)), res=a.pass_res)
    if not a.pass_spp:
        # the pool a render of this scene would use (memory budget, light sub-paths, next-event segments)
        derived = _integrator("segment_bdf", a.max_depth)
        pixels = film_sample_count(scene.sensors()[0].film())
        a.pass_spp = derived.pool_spp(pixels, derived.next_event_for(scene, pixels), derived.light_ratio_for(scene))
    integrator = _integrator("segment_bdf", a.max_depth, spp_per_pass=a.pass_spp)
    # path's walks have the distribution of the pool's camera walks: its time per camera segment of the pool,
    # rendered in turn with the passes
    s = _bdf_pass(scene, integrator, a.pass_spp, a.reps, alongside=_integrator("path", a.max_depth))
    over = (s["time_system"] + s["time_solve"]) / s["time_trace"]
    over_gather = (s["time_system"] + s["time_solve"] - s.get("time_rows", 0.0)) / s["time_trace"]
    verdict = "PASS" if over <= OVERHEAD_TARGET else "MISS"
    t_path = s["time_alongside"]
    ns_path = t_path / max(1, s["camera_segments"]) * 1e9
    ns_trace = s["time_trace"] / max(1, s["segments"]) * 1e9
    trace_ratio = ns_trace / ns_path
    rest = s["time_trace"] - s["time_camera_walks"] - s["time_light_walks"]
    return [
        "",
        f"[per-pass breakdown] segment_bdf, {scene_stem(a.pass_scene)} {a.pass_res}x{a.pass_res}, "
        f"spp_per_pass {a.pass_spp}, max_depth {a.max_depth}, fastest of {a.reps} warm passes per stage",
        f"  passes {s['passes']:.0f}, {_kernel(s)[0]} {_kernel(s)[2]:.4g}, segments {s['segments']:.0f}, "
        f"edges {s['edges']:.0f} ({s['edges'] / max(1, s['segments']):.1f}/segment), queries gathered through "
        f"Lambertian cluster sums {s.get('lumped', 0):.0f}",
        f"  trace   {_fmt_s(s['time_trace']):>9}   ({ns_trace:.0f} ns per segment; path {_fmt_s(t_path)} at the "
        f"same spp, {ns_path:.0f} ns per camera segment of the pool: {trace_ratio:.2f} x, target <= "
        f"{TRACE_TARGET:g} x: {'PASS' if trace_ratio <= TRACE_TARGET else 'MISS'}; median of the passes' own "
        f"ratios, each against path rendered right after it: {s['trace_per_segment_ratio']:.2f} x)",
        f"    camera walks {_fmt_s(s['time_camera_walks'])} ({s['time_camera_walks'] / t_path:.2f} x path's time "
        f"for the same camera paths), light walks {_fmt_s(s['time_light_walks'])} ({s['light_segments']:.0f} "
        f"segments from {s['light_paths']:.0f} light sub-paths), the rest {_fmt_s(rest)} (building the pool "
        "from the records, next-event records)",
        f"  system  {_fmt_s(s['time_system']):>9}   (grid + denominators + edge weights)",
        f"  solve   {_fmt_s(s['time_solve']):>9}   (MMIS levels + splat, and the rows' emitter and final-gathering "
        f"samples, docs/maths.md §4.7-4.9: {_fmt_s(s.get('time_rows', 0.0))} of it)",
        f"  apart   {_fmt_s(s.get('time_apart', 0.0)):>9}   (camera samples of direct light apart from the pool, "
        "docs/maths.md §4.10)",
        f"  render  {_fmt_s(s['wall']):>9}   (wall, develop included)",
        f"  filtering overhead (system + solve) / trace = {over:.2f} x   (target <= {OVERHEAD_TARGET:g} x: "
        f"{verdict}, informative); without the rows' samples, which trace rays: {over_gather:.2f} x",
    ]


def _population_part(a: argparse.Namespace) -> list[str]:
    scene = mi.load_file(str(scene_file(a.pass_scene)), res=a.pop_res)
    probe = _integrator("segment_bdf", a.max_depth, spp_per_pass=1)
    _timed_render(scene, probe, 1, seed=0)
    what, prop, size = _kernel(probe.last_stats)
    lines = [
        "",
        f"[pass time vs population] segment_bdf, {scene_stem(a.pass_scene)} {a.pop_res}x{a.pop_res}, fixed "
        f"{what} {size:.4g} (derived at spp 1), one pass, fastest of {a.reps} per stage",
    ]
    head = f"  {'spp/pass':>8} {'segments':>9} {'lumped':>8} {'edges':>10} {'edges/seg':>9} {'trace':>9} " \
           f"{'system':>9} {'solve':>9} {'pass':>9} {'us/segment':>10} {'ns/edge':>8}"
    lines += [head, "  " + "-" * (len(head) - 2)]
    rows: list[tuple[float, float, float, float]] = []  # segments, edges, pass time, system + solve
    for k in a.pop_spp:
        integrator = _integrator("segment_bdf", a.max_depth, spp_per_pass=k, **{prop: size})
        s = _bdf_pass(scene, integrator, k, a.reps)
        total = s["time_trace"] + s["time_system"] + s["time_solve"]
        seg, edges = max(1.0, s["segments"]), max(1.0, s["edges"])
        rows.append((seg, edges, total, s["time_system"] + s["time_solve"]))
        lines.append(f"  {k:>8} {seg:>9.0f} {s.get('lumped', 0):>8.0f} {edges:>10.0f} {edges / seg:>9.1f} "
                     f"{_fmt_s(s['time_trace']):>9} "
                     f"{_fmt_s(s['time_system']):>9} {_fmt_s(s['time_solve']):>9} {_fmt_s(total):>9} "
                     f"{total / seg * 1e6:>10.2f} {(s['time_system'] + s['time_solve']) / edges * 1e9:>8.1f}")
    if len(rows) > 1:
        seg, edges, total, filt = (np.log(np.asarray(c)) for c in zip(*rows, strict=True))
        r = (rows[-1][2] / rows[-1][0]) / (rows[0][2] / rows[0][0])
        word = "close to linear" if 0.8 <= r <= 1.25 else ("superlinear" if r > 1.25 else
                                                             "sublinear (fixed costs amortized)")
        lines += [
            f"  time/segment at spp {a.pop_spp[-1]} / at spp {a.pop_spp[0]} = {r:.2f}: {word}",
            f"  log-log exponents: pass time ~ segments^{np.polyfit(seg, total, 1)[0]:.2f}, edges ~ "
            f"segments^{np.polyfit(seg, edges, 1)[0]:.2f}, (system + solve) ~ edges^"
            f"{np.polyfit(edges, filt, 1)[0]:.2f}   (ns/edge: system + solve per edge)",
        ]
    return lines


# --- entry points ------------------------------------------------------------------------------------------


def run(args: list[str] | None = None) -> str:
    """Run the benchmark and return its tables (``main`` prints them)."""
    ap = argparse.ArgumentParser(prog="segmitsuba.benchmarks.filtering", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=None, help=f"comma-separated scenes (default {DEFAULT_SCENES})")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated integrators (path first)")
    ap.add_argument("--res", type=int, default=None, help=f"time-to-error resolution (default {DEFAULT_RES})")
    ap.add_argument("--cap", type=float, default=None, help="seconds of timed renders per method (default 8)")
    ap.add_argument("--at-spp", type=int, default=64, help="path's spp whose time is the equal time T")
    ap.add_argument("--spp0", type=int, default=4, help="first spp of each curve (doubled after each render)")
    ap.add_argument("--max-spp", type=int, default=1 << 16, help="largest spp of a curve")
    ap.add_argument("--ref-spp", type=int, default=4096, help="spp of a reference rendered here (res != 32)")
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--pass-scene", default="cornell", help="scene of parts 2 and 3")
    ap.add_argument("--pass-res", type=int, default=None, help="resolution of the breakdown (default 64)")
    ap.add_argument("--pass-spp", type=int, default=0,
                    help="spp_per_pass of the breakdown (default: the pool a render of the scene uses)")
    ap.add_argument("--pop-res", type=int, default=None, help="resolution of part 3 (default 64)")
    ap.add_argument("--pop-spp", default=None, help="comma-separated spp_per_pass of part 3 (default 1,2,4,8)")
    ap.add_argument("--reps", type=int, default=None, help="timed passes in parts 2 and 3 (best; default 3)")
    ap.add_argument("--parts", default="1,2,3", help="which parts to run")
    ap.add_argument("--quick", action="store_true", help="smoke run: cornell only, 1.5 s cap, res 32 passes")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    a = ap.parse_args(args)

    quick = a.quick
    a.scenes = [scene_stem(s) for s in (a.scenes or ("cornell" if quick else DEFAULT_SCENES)).split(",") if s]
    a.methods = [m for m in a.methods.split(",") if m]
    if a.methods[0] != "path":
        a.methods = ["path", *(m for m in a.methods if m != "path")]
    a.res = a.res or DEFAULT_RES
    a.cap = a.cap if a.cap is not None else (1.5 if quick else 8.0)
    a.pass_res = a.pass_res or (32 if quick else 64)
    a.pop_res = a.pop_res or (32 if quick else 64)
    a.pop_spp = [int(x) for x in (a.pop_spp or ("1,2" if quick else "1,2,4,8")).split(",") if x]
    a.reps = a.reps or (1 if quick else 3)
    parts = {p.strip() for p in a.parts.split(",")}

    mi.set_variant(a.variant)
    t_start = time.perf_counter()
    lines = [
        f"filtering benchmark: {dr.thread_count()} threads, LLVM "
        f"{'.'.join(str(v) for v in dr.detail.llvm_version())}, variant {mi.variant()}"
        + (" (quick)" if quick else "")
    ]
    if "1" in parts:
        body, summary = _time_to_error_part(a, a.scenes)
        lines += body
        lines += ["", "[time-to-error ratio vs path] (time path needs for the relMSE a method reaches at equal "
                  "time T) / T; > 1: faster than path; * extrapolated; "
                  "< upper bound (path's first point already beats it)"]
        width = max(10, *(len(s) for s in a.scenes))
        lines.append(f"  {'method':<12} " + " ".join(f"{s:>{width}}" for s in a.scenes) + f" {'geomean':>8}")
        for m in a.methods:
            vals = [summary[m][s] for s in a.scenes]
            nums = [float(v.strip("<*")) for v in vals]
            geo = statistics.geometric_mean(nums) if all(x > 0 for x in nums) else float("nan")
            lines.append(f"  {m:<12} " + " ".join(f"{v:>{width}}" for v in vals) + f" {geo:>8.2f}")
    if "2" in parts:
        lines += _breakdown_part(a)
    if "3" in parts:
        lines += _population_part(a)
    lines += ["", f"total {time.perf_counter() - t_start:.0f} s"]
    return "\n".join(lines)


def main() -> None:
    print(run())


if __name__ == "__main__":
    main()
