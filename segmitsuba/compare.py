"""Equal-time comparison of integrators against a reference: the library behind ``segmitsuba compare SCENE``.

Each method renders the scene in passes until its time budget is spent. After every pass the running image
(the exact sample-weighted average of the passes so far) is compared with the reference; each such
*checkpoint* records the render time so far (the sum of the passes' times, synchronized with
``dr.sync_thread``; the metric evaluation itself is not counted), the spp and the metrics of
:mod:`segmitsuba.metrics`. Pass sizes double the total spp each time (1, 1, 2, 4, ... spp), so the checkpoints
are evenly spread on a log time axis; a pass is shrunk to fit the budget and no pass starts that would not fit.
Before timing, every method renders one untimed 1-spp pass so that JIT compilation is not counted
(``warmup=False`` counts it).

The reference: :func:`stored_reference` is the stored converged reference of :mod:`segmitsuba.references` when
the scene is one of ``scenes/*.xml`` at res 32 and max_depth 8 (and no define changes the scene); otherwise
:func:`render_reference` renders one with ``path`` for 8x the per-method budget. ``segmitsuba compare
--reference auto`` (the default) takes the first that applies and says which, in its output and in
results.json; ``--reference FILE.exr`` uses that file.

Outputs (:func:`write_results`; ``segmitsuba compare --out``, default ``out/compare_<scene>/``):
``error_vs_time.png`` (log-log relMSE vs seconds), ``grid.png`` (final images and the reference, with two zoomed
crops where the methods' errors differ most), ``results.json`` (:func:`results_record`), ``results.csv`` (one
row per checkpoint) and ``<method>.exr`` / ``reference.exr``.

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

import csv
import json
import math
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

    result = render_passes(scene, integrator, time_budget=time_budget,
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


#: seed of the first pass of a rendered reference (the methods' runs default to seed 0)
REFERENCE_SEED = 987654321


def render_reference(scene: Any, max_depth: int, method_time: float) -> tuple[np.ndarray, dict[str, Any]]:
    """A reference for a scene without a stored one: ``path`` (``max_depth``) rendered for
    :data:`REFERENCE_FACTOR` x ``method_time`` seconds. Returns the RGB image and its description for
    ``results.json``; errors below the reference's own noise are not meaningful."""
    import mitsuba as mi

    from .rendering import render_passes

    budget = REFERENCE_FACTOR * method_time
    result = render_passes(scene, mi.load_dict({"type": "path", "max_depth": max_depth}),
                           time_budget=budget, seed=REFERENCE_SEED, progress=False, handle_sigint=False)
    info = {"source": "rendered", "integrator": "path", "spp": result.spp,
            "seconds": result.seconds, "seed": REFERENCE_SEED,
            "note": f"rendered here with path for {REFERENCE_FACTOR}x the per-method time budget"}
    return result.image[..., :3], info


def results_record(runs: Sequence[MethodRun], reference: dict[str, Any], settings: dict[str, Any]) -> dict[str, Any]:
    """The content of ``results.json``: ``settings`` (which must hold ``width``, ``height`` and ``warmup``)
    followed by the date, the metric definitions and what the times count; the ``reference``'s description;
    the machine (:func:`segmitsuba.rendering.environment`); per method its properties, final metrics and
    checkpoints."""
    from .rendering import environment

    env = environment()
    settings = {**settings, "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                "metrics": {"relmse_eps": metrics.RELMSE_EPS, "trim": 0.001, "flip": metrics.FLIP_MODE,
                            "flip_at_checkpoints": settings["width"] * settings["height"] <= FLIP_ALL_PIXELS},
                "timing": "render seconds: sum of the passes (dr.sync_thread), metrics excluded"
                + ("; JIT compilation excluded (untimed 1-spp warm-up pass)" if settings["warmup"] else "")}
    return {
        "settings": settings,
        "reference": reference,
        "machine": env,
        "methods": {r.method: {"params": r.params, "integrator": r.integrator, "compile_seconds": r.compile_seconds,
                               "final": r.final, "checkpoints": [asdict(c) for c in r.checkpoints]} for r in runs},
    }


def write_results(out: Path, runs: Sequence[MethodRun], ref: np.ndarray, results: dict[str, Any], name: str,
                  exposure: float = 0.0) -> dict[str, Path]:
    """Write a comparison to the existing folder ``out``: ``error_vs_time.png`` (titled with the scene's
    ``name``), ``grid.png`` (``exposure`` in EV), ``results.json`` (``results``, see :func:`results_record`),
    ``results.csv`` and the final images ``<method>.exr`` and ``reference.exr``. Returns the paths of the
    first four by kind (error_vs_time, grid, json, csv); raises OSError where a file cannot be written."""
    from . import __version__
    from .imageio import write_exr

    settings, reference = results["settings"], results["reference"]
    floor = reference.get("expected_relmse")
    title = f"{name} {settings['width']}x{settings['height']}, max_depth {settings['max_depth']}, " \
            f"{settings['time_budget']:g} s/method; reference: {reference['source']} " \
            f"{reference.get('integrator') or ''} {reference.get('spp') or ''} spp"
    paths = {"error_vs_time": out / "error_vs_time.png", "grid": out / "grid.png",
             "json": out / "results.json", "csv": out / "results.csv"}
    paths["json"].write_text(json.dumps(results, indent=2, default=_json_default))
    write_csv(runs, paths["csv"])
    plot_error_vs_time(runs, paths["error_vs_time"], title, float(floor) if floor else None)
    plot_grid(runs, ref, paths["grid"], exposure)
    meta = {"software": f"segmitsuba {__version__}", "scene": settings["scene"]}
    for r in runs:
        assert r.image is not None
        write_exr(out / f"{r.method}.exr", r.image, ["R", "G", "B"],
                  {**meta, "integrator": r.method, "spp": r.final["spp"], "render_time": r.final["time"]})
    write_exr(out / "reference.exr", np.asarray(ref).astype(np.float32), ["R", "G", "B"], {**meta, **{
        k: v for k, v in reference.items() if isinstance(v, (str, int, float))}})
    return paths


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)
