"""Equal-time comparison of integrators against a reference: ``segmitsuba compare SCENE``.

Each method renders the scene in passes until its time budget is spent. After every pass the running image
(the exact sample-weighted average of the passes so far) is compared with the reference; each such
*checkpoint* records the render time so far (the sum of the passes' times, synchronized with
``dr.sync_thread``; the metric evaluation itself is not counted), the spp and the metrics of
:mod:`segmitsuba.metrics`. Pass sizes double the total spp each time (1, 1, 2, 4, ... spp), so the checkpoints
are evenly spread on a log time axis; a pass is shrunk to fit the budget and no pass starts that would not fit.
Before timing, every method renders one untimed 1-spp pass so that JIT compilation is not counted
(``warmup=False`` counts it).

The reference: ``--reference auto`` (default) uses the stored converged reference of
:mod:`segmitsuba.references` when SCENE is one of ``scenes/*.xml`` at res 32 and max_depth 8 (and no -D define
changes the scene), and otherwise renders one with ``path`` for 8x the per-method budget (and says so, in the
output and in results.json). ``--reference FILE.exr`` uses that file.

Outputs (``--out``, default ``out/compare_<scene>/``): ``error_vs_time.png`` (log-log relMSE vs seconds),
``grid.png`` (final images and the reference, with two zoomed crops where the methods' errors differ most),
``results.json``, ``results.csv`` (one row per checkpoint) and ``<method>.exr`` / ``reference.exr``.

From Python::

    import segmitsuba
    import mitsuba as mi
    from segmitsuba.compare import compare_methods

    mi.set_variant("llvm_ad_rgb")
    scene = mi.load_file("scenes/cornell.xml", res=32)
    runs = compare_methods(scene, ref, ["path", "segment_bdf"], time_budget=5)   # ref: H x W x 3 numpy
    print(runs[0].checkpoints[-1].relmse)
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import metrics

DEFAULT_METHODS = ("path", "segment_pt", "segment_mvf", "segment_pf", "segment_bdf")
DEFAULT_TIME = 10.0
DEFAULT_RES = 32
DEFAULT_MAX_DEPTH = 8
#: FLIP at every checkpoint up to this many pixels, else only for the final images (it costs ~25 ms at 32x32)
FLIP_ALL_PIXELS = 128 * 128
#: the auto reference renders with path for this many times the per-method budget
REFERENCE_FACTOR = 8
#: defines that do not change what the scene looks like to an explicit integrator
NEUTRAL_DEFINES = frozenset({"spp", "integrator", "max_depth"})
#: samples (pixels x spp) per pass at most: bounds a pass's memory as ``segmitsuba.rendering`` does
PASS_SAMPLES = 2**20


@dataclass
class Checkpoint:
    """The running image after one pass, compared with the reference."""

    index: int  #: 0-based pass index
    time: float  #: render seconds so far (sum of the timed passes)
    spp: int  #: samples per pixel so far
    pass_spp: int
    pass_seconds: float
    relmse: float
    relmse_trimmed: float
    mse: float
    flip: float | None  #: None where FLIP is only computed for the final image


@dataclass
class MethodRun:
    """One method's equal-time run."""

    method: str
    params: dict[str, Any]  #: integrator properties (max_depth included)
    integrator: str  #: the integrator's description (str(integrator)), first line
    checkpoints: list[Checkpoint] = field(default_factory=list)
    final: dict[str, float] = field(default_factory=dict)  #: every metric of the final image, FLIP included
    compile_seconds: float = 0.0  #: the untimed warm-up pass (0 without warm-up)
    image: np.ndarray | None = None  #: the final image (H x W x 3)


def _evaluate(image: np.ndarray, ref: np.ndarray, with_flip: bool) -> dict[str, float | None]:
    return {
        "relmse": metrics.relmse(image, ref),
        "relmse_trimmed": metrics.relmse_trimmed(image, ref),
        "mse": metrics.mse(image, ref),
        "flip": metrics.flip(image, ref) if with_flip else None,
    }


def run_method(scene: Any, method: str, ref: np.ndarray, time_budget: float, params: dict[str, Any] | None = None,
               seed: int = 0, warmup: bool = True, flip_every: bool | None = None,
               say: Callable[[str], None] | None = None) -> MethodRun:
    """Render ``scene`` with integrator ``method`` (properties ``params``) in passes until ``time_budget``
    seconds of render time are spent; a checkpoint after every pass (see the module docstring)."""
    import mitsuba as mi

    from .rendering import PassReport, render_passes

    params = dict(params or {})
    integrator = mi.load_dict({"type": method, **params})
    size = scene.sensors()[0].film().crop_size()
    pixels = int(size[0]) * int(size[1])
    ref = np.asarray(ref, dtype=np.float64)[..., :3]
    if flip_every is None:
        flip_every = pixels <= FLIP_ALL_PIXELS
    run = MethodRun(method, params, str(integrator).splitlines()[0] if str(integrator) else method)

    def checkpoint(r: PassReport) -> None:
        assert r.image is not None
        image = r.image()[..., :3]
        if image.shape != ref.shape:
            raise ValueError(f"{method} renders {image.shape[1]}x{image.shape[0]} but the reference is "
                             f"{ref.shape[1]}x{ref.shape[0]}")
        m = _evaluate(image, ref, flip_every)
        run.checkpoints.append(Checkpoint(r.index, r.seconds, r.spp, r.pass_spp, r.pass_seconds, m["relmse"],
                                          m["relmse_trimmed"], m["mse"], m["flip"]))
        if say is not None:
            say(f"  {method}: pass {r.index + 1}, {r.spp} spp, {r.seconds:.2f}/{time_budget:g} s, "
                f"relMSE {m['relmse']:.3e}")

    result = render_passes(scene, integrator, time_budget=time_budget, pass_spp=max(1, PASS_SAMPLES // pixels),
                           seed=seed, progress=False, callback=checkpoint, handle_sigint=False, growth="doubling",
                           warmup=warmup)
    run.compile_seconds = result.warmup_seconds
    run.image = result.image[..., :3].astype(np.float32)
    final = _evaluate(run.image, ref, True)
    run.final = {"time": result.seconds, "spp": result.spp, "passes": result.passes, **final}
    return run


def compare_methods(scene: Any, ref: np.ndarray, methods: Sequence[str], time_budget: float,
                    params: dict[str, dict[str, Any]] | None = None, max_depth: int = DEFAULT_MAX_DEPTH,
                    seed: int = 0, warmup: bool = True, say: Callable[[str], None] | None = None) -> list[MethodRun]:
    """:func:`run_method` for each method, with ``max_depth`` unless ``params[method]`` sets it."""
    runs = []
    for method in methods:
        props = {"max_depth": max_depth, **(params or {}).get(method, {})}
        if say is not None:
            say(f"{method}: {time_budget:g} s" + (f" ({_fmt_params(props)})" if props else ""))
        runs.append(run_method(scene, method, ref, time_budget, props, seed, warmup, say=say))
    return runs


def _fmt_params(props: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in props.items())


# --- outputs -----------------------------------------------------------------------------------------------


def plot_error_vs_time(runs: Sequence[MethodRun], path: Path, title: str = "",
                       floor: float | None = None) -> None:
    """Log-log relMSE vs render seconds, one line per method, a marker per checkpoint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5), dpi=120)
    for run in runs:
        t = [c.time for c in run.checkpoints]
        e = [max(c.relmse, 1e-12) for c in run.checkpoints]
        ax.loglog(t, e, marker="o", markersize=4, label=f"{run.method} ({run.final['relmse']:.2e})")
    if floor is not None and floor > 0:
        ax.axhline(floor, color="grey", linestyle="--", linewidth=1, label=f"reference noise ~{floor:.1e}")
    ax.set_xlabel("render time (s)")
    ax.set_ylabel("relMSE vs reference")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _window_sums(x: np.ndarray, c: int) -> np.ndarray:
    """Sums of ``x`` over every c x c window (top-left corners), shape (H - c + 1, W - c + 1)."""
    s = np.pad(np.cumsum(np.cumsum(x, axis=0), axis=1), ((1, 0), (1, 0)))
    return s[c:, c:] - s[:-c, c:] - s[c:, :-c] + s[:-c, :-c]


def crop_regions(images: Sequence[np.ndarray], ref: np.ndarray, count: int = 2) -> list[tuple[int, int, int]]:
    """``count`` non-overlapping square windows (y, x, side) where the per-pixel relative errors of the images
    vary most across the methods (their mean error where all agree, e.g. with one method)."""
    h, w = ref.shape[:2]
    c = max(2, min(h, w) // 5)
    errors = np.stack([np.mean(metrics.relmse_values(im[..., :3], ref[..., :3]), axis=2) for im in images])
    score = errors.var(axis=0) if len(images) > 1 else errors[0]
    if not np.any(score > 0):
        score = errors.mean(axis=0)
    sums = _window_sums(score, c)
    regions: list[tuple[int, int, int]] = []
    for _ in range(count):
        y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
        regions.append((int(y), int(x), c))
        y0, x0 = max(0, y - c + 1), max(0, x - c + 1)
        sums[y0:y + c, x0:x + c] = -np.inf  # windows overlapping this one
        if not np.any(np.isfinite(sums)):
            break
    return regions


def plot_grid(runs: Sequence[MethodRun], ref: np.ndarray, path: Path, exposure: float = 0.0) -> None:
    """Final image of each method and the reference (tone-mapped), each with zoomed crops."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from .imageio import to_srgb8

    images = [r.image for r in runs]
    regions = crop_regions(images, ref)
    columns = [(r.method, r.image, f"relMSE {r.final['relmse']:.2e}\nFLIP {r.final['flip']:.3f}, "
                f"{r.final['spp']} spp") for r in runs]
    columns.append(("reference", ref, ""))
    colors = ["#ff3030", "#30c0ff", "#ffd030"]
    rows = 1 + len(regions)
    fig, axes = plt.subplots(rows, len(columns), figsize=(2.3 * len(columns), 2.3 * rows + 0.6), dpi=120,
                             squeeze=False)
    for j, (name, image, label) in enumerate(columns):
        srgb = to_srgb8(image, exposure)
        ax = axes[0][j]
        ax.imshow(srgb, interpolation="nearest")
        ax.set_title(f"{name}\n{label}" if label else f"{name}\n", fontsize=8)
        for k, (y, x, c) in enumerate(regions):
            ax.add_patch(Rectangle((x - 0.5, y - 0.5), c, c, fill=False, edgecolor=colors[k % 3], linewidth=1.2))
        for k, (y, x, c) in enumerate(regions):
            crop_ax = axes[k + 1][j]
            crop_ax.imshow(srgb[y:y + c, x:x + c], interpolation="nearest")
            for side in crop_ax.spines.values():
                side.set_edgecolor(colors[k % 3])
                side.set_linewidth(2)
            if name != "reference":
                e = metrics.relmse(image[y:y + c, x:x + c, :3], ref[y:y + c, x:x + c, :3])
                crop_ax.set_xlabel(f"crop relMSE {e:.2e}", fontsize=7)
    for row in axes:
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


CSV_FIELDS = ("method", "pass", "time", "spp", "pass_spp", "pass_seconds", "relmse", "relmse_trimmed", "mse",
              "flip", "final")


def write_csv(runs: Sequence[MethodRun], path: Path) -> None:
    """One row per checkpoint; ``final`` is 1 on each method's last row (whose FLIP is always computed)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_FIELDS)
        for run in runs:
            for k, c in enumerate(run.checkpoints):
                last = k == len(run.checkpoints) - 1
                flip = run.final["flip"] if last else c.flip
                writer.writerow([run.method, c.index, f"{c.time:.6g}", c.spp, c.pass_spp, f"{c.pass_seconds:.6g}",
                                 f"{c.relmse:.6g}", f"{c.relmse_trimmed:.6g}", f"{c.mse:.6g}",
                                 "" if flip is None else f"{flip:.6g}", int(last)])


def summary_table(runs: Sequence[MethodRun]) -> str:
    """Final metrics per method; ``eff/path`` = (relMSE x time of path) / (relMSE x time), > 1: more efficient."""
    base = next((r.final for r in runs if r.method == "path"), None)
    head = f"{'method':<12} {'passes':>6} {'spp':>7} {'time s':>7} {'relMSE':>9} {'trimmed':>9} {'MSE':>9} " \
           f"{'FLIP':>6} {'eff/path':>8}"
    lines = [head, "-" * len(head)]
    for r in runs:
        f = r.final
        eff = ""
        if base is not None and f["relmse"] > 0 and f["time"] > 0:
            eff = f"{base['relmse'] * base['time'] / (f['relmse'] * f['time']):.3g}"
        lines.append(f"{r.method:<12} {f['passes']:>6} {f['spp']:>7} {f['time']:>7.2f} {f['relmse']:>9.3e} "
                     f"{f['relmse_trimmed']:>9.3e} {f['mse']:>9.3e} {f['flip']:>6.3f} {eff:>8}")
    return "\n".join(lines)


# --- reference ---------------------------------------------------------------------------------------------


def stored_reference(scene_path: Path, res: int, max_depth: int,
                     defines: dict[str, str]) -> tuple[np.ndarray, dict[str, Any]] | None:
    """The stored reference of ``scene_path`` if it is one of scenes/*.xml at res 32 / max_depth 8, no define
    changes the scene, the file exists and is not stale; else None."""
    from . import references

    stem = references.scene_stem(scene_path)
    if res != references.DEFAULT_RES or max_depth != references.DEFAULT_MAX_DEPTH:
        return None
    if set(defines) - NEUTRAL_DEFINES or stem not in references.reference_scenes():
        return None
    if Path(scene_path).resolve() != references.scene_file(stem).resolve():
        return None
    try:
        image, meta = references.load_reference(stem, res, max_depth)
    except FileNotFoundError:
        return None
    if references.stale_reason(meta, stem) is not None:
        return None
    return image[..., :3], meta


# --- command line ------------------------------------------------------------------------------------------


def add(subparsers: Any) -> None:
    """Add the ``compare`` subcommand (registered in :data:`segmitsuba.cli.COMMANDS`)."""
    from .cli import key_value, positive_float, positive_int, seed_int

    p = subparsers.add_parser(
        "compare", help="equal-time comparison of integrators against a reference (plots, grid, JSON/CSV)",
        description="Render SCENE with each method for the same time budget, in passes, recording after each pass "
        "the error of the running average against a reference (relMSE, trimmed relMSE, MSE, FLIP). Writes "
        "error_vs_time.png, grid.png, results.json, results.csv and the final EXRs to --out.",
    )
    p.add_argument("scene", metavar="SCENE", help="scene file (or the name of one in scenes/, e.g. cornell)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated integrators (default: {','.join(DEFAULT_METHODS)})")
    p.add_argument("--time", type=positive_float, default=DEFAULT_TIME, metavar="SECONDS",
                   help=f"render time per method (default: {DEFAULT_TIME:g})")
    p.add_argument("--res", type=positive_int, default=DEFAULT_RES,
                   help=f"image side, the scene's $res (default: {DEFAULT_RES})")
    p.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH,
                   help=f"max_depth of every method (default: {DEFAULT_MAX_DEPTH})")
    p.add_argument("--reference", default="auto", metavar="EXR|auto",
                   help="reference image; auto: the stored one for scenes/*.xml at res 32 / max_depth 8, else "
                   f"path for {REFERENCE_FACTOR}x --time")
    p.add_argument("--out", metavar="DIR", help="output folder (default: out/compare_<scene>/)")
    p.add_argument("-D", dest="defines", action="append", type=key_value, default=[], metavar="NAME=VALUE",
                   help="scene parameter ($NAME in the scene file), repeatable")
    p.add_argument("--param", dest="params", action="append", type=key_value, default=[],
                   metavar="METHOD.KEY=VALUE", help="integrator property of one method (METHOD 'all': every "
                   "method), repeatable")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the first pass (default: 0)")
    p.add_argument("--no-warmup", dest="warmup", action="store_false",
                   help="count JIT compilation (by default an untimed 1-spp pass compiles first)")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="exposure of grid.png")
    p.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default: llvm_ad_rgb)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _method_params(methods: Sequence[str], pairs: Sequence[tuple[str, str]]) -> dict[str, dict[str, Any]]:
    from .cli import CliError, parse_value

    out: dict[str, dict[str, Any]] = {m: {} for m in methods}
    for key, value in pairs:
        method, dot, prop = key.partition(".")
        if not dot or not prop:
            raise CliError(f"--param expects METHOD.KEY=VALUE, got '{key}={value}'")
        targets = list(methods) if method == "all" else [method]
        if method != "all" and method not in out:
            raise CliError(f"--param '{key}': '{method}' is not one of the methods ({', '.join(methods)})")
        for m in targets:
            out[m][prop] = parse_value(value)
    return out


def _scene_path(name: str) -> Path:
    from . import references
    from .cli import CliError

    path = Path(name)
    if path.is_file():
        return path
    if not path.exists() and path.suffix == "" and references.scene_file(name).is_file():
        return references.scene_file(name)
    if path.exists():
        raise CliError(f"scene '{path}' is not a file")
    raise CliError(f"scene file '{path}' does not exist")


def _prepare_out(out: Path) -> None:
    from .cli import CliError

    if out.exists() and not out.is_dir():
        raise CliError(f"--out '{out}' is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".segmitsuba-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise CliError(f"output folder '{out}' is not writable: {e.strerror or e}") from None


def run(args: argparse.Namespace) -> int:
    import mitsuba as mi

    from . import __version__
    from .cli import EXIT_FAILURE, CliError, _not_found, _set_variant, mitsuba_message
    from .imageio import read_exr, write_exr
    from .references import reference_path
    from .rendering import environment, render_passes

    say = (lambda _m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise CliError("--methods is empty")
    if len(set(methods)) != len(methods):
        raise CliError(f"--methods lists a method twice: {args.methods}")
    if args.max_depth == 0 or args.max_depth < -1:
        raise CliError(f"--max-depth must be -1 (unbounded) or positive, got {args.max_depth}")
    params = _method_params(methods, args.params)
    scene_path = _scene_path(args.scene)
    defines = dict(args.defines)
    if "res" in defines:
        raise CliError("give the image size with --res, not -D res=...")
    stem = scene_path.stem
    out = Path(args.out) if args.out else Path("out") / f"compare_{stem}"
    _prepare_out(out)
    _set_variant(args.variant)

    try:
        scene = mi.load_file(str(scene_path), res=args.res, **defines)
    except Exception as e:
        msg = mitsuba_message(e)
        hint = " (the scene has no $res parameter: --res needs one)" if "$res" in msg else ""
        raise CliError(f"cannot load scene '{scene_path}': {msg}{hint}") from None
    for m in methods:  # fail on a bad method or property before rendering anything
        props = {"max_depth": args.max_depth, **params[m]}
        try:
            integrator = mi.load_dict({"type": m, **props})
        except Exception as e:
            if _not_found(e, m):
                raise CliError(f"unknown method '{m}' (an integrator plugin, e.g. {', '.join(DEFAULT_METHODS)})") \
                    from None
            raise CliError(f"cannot create method '{m}' ({_fmt_params(props)}): {mitsuba_message(e)}") from None
        if not isinstance(integrator, mi.Integrator):
            raise CliError(f"method '{m}' is a {type(integrator).__name__} plugin, not an integrator")

    size = scene.sensors()[0].film().crop_size()
    w, h = int(size[0]), int(size[1])
    ref_info: dict[str, Any]
    if args.reference != "auto":
        ref_path = Path(args.reference)
        if not ref_path.is_file():
            raise CliError(f"reference '{ref_path}' does not exist")
        try:
            ref, meta = read_exr(ref_path)
        except Exception as e:
            raise CliError(f"cannot read reference '{ref_path}': {e}") from None
        if ref.shape[:2] != (h, w) or ref.ndim != 3 or ref.shape[2] < 3:
            raise CliError(f"reference '{ref_path}' is {ref.shape[1]}x{ref.shape[0]} (channels "
                           f"{ref.shape[2:] or 1}) but the scene renders {w}x{h} RGB")
        ref = ref[..., :3]
        ref_info = {"source": "file", "path": str(ref_path.resolve()),
                    "integrator": meta.get("integrator"), "spp": meta.get("spp")}
        say(f"reference: {ref_path}")
    else:
        stored = stored_reference(scene_path, args.res, args.max_depth, defines)
        if stored is not None:
            ref, meta = stored
            ref_info = {"source": "stored", "path": str(reference_path(stem, args.res, args.max_depth)),
                        "integrator": meta.get("integrator"), "spp": meta.get("spp"),
                        "expected_relmse": meta.get("expected_relmse", meta.get("half_relmse"))}
            say(f"reference: stored {ref_info['path']} ({meta.get('integrator')}, {meta.get('spp')} spp)")
        else:
            budget = REFERENCE_FACTOR * args.time
            say(f"reference: no stored one for this scene/res/max_depth/defines; rendering path for {budget:g} s "
                f"({REFERENCE_FACTOR}x the per-method budget), so errors below its own noise are not meaningful")
            try:
                result = render_passes(scene, mi.load_dict({"type": "path", "max_depth": args.max_depth}),
                                       time_budget=budget, seed=987654321, progress=False, handle_sigint=False)
            except Exception as e:
                raise CliError(f"reference render failed: {mitsuba_message(e)}", EXIT_FAILURE) from None
            ref = result.image[..., :3]
            ref_info = {"source": "rendered", "integrator": "path", "spp": result.spp,
                        "seconds": result.seconds, "seed": 987654321,
                        "note": f"rendered here with path for {REFERENCE_FACTOR}x the per-method time budget"}
    ref = np.asarray(ref, dtype=np.float64)
    if not np.all(np.isfinite(ref)):
        raise CliError("the reference has NaN or inf values")

    say(f"comparing {', '.join(methods)} on {scene_path} ({w}x{h}, max_depth {args.max_depth}), "
        f"{args.time:g} s each")
    try:
        runs = compare_methods(scene, ref, methods, args.time, params, args.max_depth, args.seed, args.warmup,
                               say=say)
    except KeyboardInterrupt:
        raise
    except Exception as e:
        raise CliError(f"compare failed: {mitsuba_message(e)}", EXIT_FAILURE) from None

    env = environment()
    settings = {"scene": str(scene_path.resolve()), "defines": defines, "res": args.res, "width": w, "height": h,
                "max_depth": args.max_depth, "time_budget": args.time, "seed": args.seed, "warmup": args.warmup,
                "methods": methods, "command": " ".join(["segmitsuba", *sys.argv[1:]]),
                "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                "metrics": {"relmse_eps": metrics.RELMSE_EPS, "trim": 0.001, "flip": metrics.FLIP_MODE,
                            "flip_at_checkpoints": w * h <= FLIP_ALL_PIXELS},
                "timing": "render seconds: sum of the passes (dr.sync_thread), metrics excluded"
                + ("; JIT compilation excluded (untimed 1-spp warm-up pass)" if args.warmup else "")}
    results = {
        "settings": settings,
        "reference": ref_info,
        "machine": env,
        "methods": {r.method: {"params": r.params, "integrator": r.integrator, "compile_seconds": r.compile_seconds,
                               "final": r.final, "checkpoints": [asdict(c) for c in r.checkpoints]} for r in runs},
    }
    floor = ref_info.get("expected_relmse")
    title = f"{stem} {w}x{h}, max_depth {args.max_depth}, {args.time:g} s/method; reference: {ref_info['source']} " \
            f"{ref_info.get('integrator') or ''} {ref_info.get('spp') or ''} spp"
    paths = {"error_vs_time": out / "error_vs_time.png", "grid": out / "grid.png",
             "json": out / "results.json", "csv": out / "results.csv"}
    try:
        paths["json"].write_text(json.dumps(results, indent=2, default=_json_default))
        write_csv(runs, paths["csv"])
        plot_error_vs_time(runs, paths["error_vs_time"], title, float(floor) if floor else None)
        plot_grid(runs, ref, paths["grid"], args.exposure)
        meta = {"software": f"segmitsuba {__version__}", "scene": str(scene_path.resolve())}
        for r in runs:
            assert r.image is not None
            write_exr(out / f"{r.method}.exr", r.image, ["R", "G", "B"],
                      {**meta, "integrator": r.method, "spp": r.final["spp"], "render_time": r.final["time"]})
        write_exr(out / "reference.exr", ref.astype(np.float32), ["R", "G", "B"], {**meta, **{
            k: v for k, v in ref_info.items() if isinstance(v, (str, int, float))}})
    except OSError as e:
        raise CliError(f"cannot write the results: {e.strerror or e}", EXIT_FAILURE) from None

    print(f"{stem} {w}x{h}, {args.time:g} s per method, reference: {ref_info['source']} "
          f"({ref_info.get('integrator')}, {ref_info.get('spp')} spp)")
    print(summary_table(runs))
    for p in paths.values():
        print(f"wrote {p}")
    sys.stdout.flush()
    return 0


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)
