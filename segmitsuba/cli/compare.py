"""``segmitsuba compare SCENE``: equal-time runs of integrators against a reference (:mod:`segmitsuba.compare`),
written as plots, an image grid, JSON/CSV and EXRs to an output folder, with a summary table on stdout."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import compare as comparison
from .. import references
from ..compare import DEFAULT_MAX_DEPTH, DEFAULT_METHODS, DEFAULT_RES, DEFAULT_TIME, REFERENCE_FACTOR
from .common import (
    DEFAULT_VARIANT,
    EXIT_FAILURE,
    CliError,
    check_max_depth,
    format_params,
    key_value,
    mitsuba_message,
    parse_value,
    plugin_not_found,
    positive_float,
    positive_int,
    prepare_out_dir,
    progress_printer,
    seed_int,
    set_variant,
)


def add(sub: Any) -> None:
    """Add the ``compare`` subcommand to the subparsers ``sub``."""
    p = sub.add_parser(
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
    p.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default: {DEFAULT_VARIANT})")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def method_params(methods: Sequence[str], pairs: Sequence[tuple[str, str]]) -> dict[str, dict[str, Any]]:
    """``--param METHOD.KEY=VALUE`` pairs as properties per method (METHOD ``all``: every method)."""
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


def scene_path(name: str) -> Path:
    """SCENE as a file: a path, or the name of a scene in ``scenes/`` (``cornell``)."""
    path = Path(name)
    if path.is_file():
        return path
    if not path.exists() and path.suffix == "" and references.scene_file(name).is_file():
        return references.scene_file(name)
    if path.exists():
        raise CliError(f"scene '{path}' is not a file")
    raise CliError(f"scene file '{path}' does not exist")


def _check_methods(methods: Sequence[str], params: dict[str, dict[str, Any]], max_depth: int) -> None:
    """Fail on a bad method or property before rendering anything."""
    import mitsuba as mi

    for m in methods:
        props = {"max_depth": max_depth, **params[m]}
        try:
            integrator = mi.load_dict({"type": m, **props})
        except Exception as e:
            if plugin_not_found(e, m):
                raise CliError(f"unknown method '{m}' (an integrator plugin, e.g. {', '.join(DEFAULT_METHODS)})") \
                    from None
            raise CliError(f"cannot create method '{m}' {format_params(props)}: {mitsuba_message(e)}") from None
        if not isinstance(integrator, mi.Integrator):
            raise CliError(f"method '{m}' is a {type(integrator).__name__} plugin, not an integrator")


def _file_reference(path: Path, width: int, height: int) -> tuple[np.ndarray, dict[str, Any]]:
    """``--reference FILE.exr``: its RGB image, which must have the scene's size, and its description."""
    from ..imageio import read_exr

    if not path.is_file():
        raise CliError(f"reference '{path}' does not exist")
    try:
        ref, meta = read_exr(path)
    except Exception as e:
        raise CliError(f"cannot read reference '{path}': {e}") from None
    if ref.shape[:2] != (height, width) or ref.ndim != 3 or ref.shape[2] < 3:
        raise CliError(f"reference '{path}' is {ref.shape[1]}x{ref.shape[0]} (channels "
                       f"{ref.shape[2:] or 1}) but the scene renders {width}x{height} RGB")
    info = {"source": "file", "path": str(path.resolve()), "integrator": meta.get("integrator"),
            "spp": meta.get("spp")}
    return ref[..., :3], info


def run(args: argparse.Namespace) -> int:
    """``segmitsuba compare``: check everything, pick the reference, run the methods, write the results."""
    import mitsuba as mi

    say = progress_printer(args.quiet)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise CliError("--methods is empty")
    if len(set(methods)) != len(methods):
        raise CliError(f"--methods lists a method twice: {args.methods}")
    check_max_depth(args.max_depth)
    params = method_params(methods, args.params)
    path = scene_path(args.scene)
    defines = dict(args.defines)
    if "res" in defines:
        raise CliError("give the image size with --res, not -D res=...")
    stem = path.stem
    out = Path(args.out) if args.out else Path("out") / f"compare_{stem}"
    prepare_out_dir(out)
    set_variant(args.variant)

    try:
        scene = mi.load_file(str(path), res=args.res, **defines)
    except Exception as e:
        msg = mitsuba_message(e)
        hint = " (the scene has no $res parameter: --res needs one)" if "$res" in msg else ""
        raise CliError(f"cannot load scene '{path}': {msg}{hint}") from None
    _check_methods(methods, params, args.max_depth)

    size = scene.sensors()[0].film().crop_size()
    w, h = int(size[0]), int(size[1])
    ref_info: dict[str, Any]
    if args.reference != "auto":
        ref_path = Path(args.reference)
        ref, ref_info = _file_reference(ref_path, w, h)
        say(f"reference: {ref_path}")
    else:
        stored = comparison.stored_reference(path, args.res, args.max_depth, defines)
        if stored is not None:
            ref, meta = stored
            ref_info = {"source": "stored", "path": str(references.reference_path(stem, args.res, args.max_depth)),
                        "integrator": meta.get("integrator"), "spp": meta.get("spp"),
                        "expected_relmse": meta.get("expected_relmse", meta.get("half_relmse"))}
            say(f"reference: stored {ref_info['path']} ({meta.get('integrator')}, {meta.get('spp')} spp)")
        else:
            budget = REFERENCE_FACTOR * args.time
            say(f"reference: no stored one for this scene/res/max_depth/defines; rendering path for {budget:g} s "
                f"({REFERENCE_FACTOR}x the per-method budget), so errors below its own noise are not meaningful")
            try:
                ref, ref_info = comparison.render_reference(scene, args.max_depth, args.time)
            except Exception as e:
                raise CliError(f"reference render failed: {mitsuba_message(e)}", EXIT_FAILURE) from None
    ref = np.asarray(ref, dtype=np.float64)
    if not np.all(np.isfinite(ref)):
        raise CliError("the reference has NaN or inf values")

    say(f"comparing {', '.join(methods)} on {path} ({w}x{h}, max_depth {args.max_depth}), "
        f"{args.time:g} s each")
    try:
        runs = comparison.compare_methods(scene, ref, methods, args.time, params, args.max_depth, args.seed,
                                          args.warmup, say=say)
    except KeyboardInterrupt:
        raise
    except Exception as e:
        raise CliError(f"compare failed: {mitsuba_message(e)}", EXIT_FAILURE) from None

    settings = {"scene": str(path.resolve()), "defines": defines, "res": args.res, "width": w, "height": h,
                "max_depth": args.max_depth, "time_budget": args.time, "seed": args.seed, "warmup": args.warmup,
                "methods": methods, "command": " ".join(["segmitsuba", *sys.argv[1:]])}
    results = comparison.results_record(runs, ref_info, settings)
    try:
        paths = comparison.write_results(out, runs, ref, results, stem, args.exposure)
    except OSError as e:
        raise CliError(f"cannot write the results: {e.strerror or e}", EXIT_FAILURE) from None

    print(f"{stem} {w}x{h}, {args.time:g} s per method, reference: {ref_info['source']} "
          f"({ref_info.get('integrator')}, {ref_info.get('spp')} spp)")
    print(comparison.summary_table(runs))
    for p in paths.values():
        print(f"wrote {p}")
    sys.stdout.flush()
    return 0
