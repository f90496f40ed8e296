"""``segmitsuba render``: render a scene (default: the built-in Cornell box) in passes, locally or on a Dask
cluster, and write an EXR with the render metadata plus an sRGB PNG preview."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from .. import __version__
from .common import (
    DEFAULT_INTEGRATOR,
    DEFAULT_RES,
    DEFAULT_VARIANT,
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    CliError,
    builtin_scene,
    check_output,
    key_value,
    load_scene,
    make_integrator,
    mitsuba_message,
    parse_value,
    positive_float,
    positive_int,
    progress_printer,
    resolution,
    seed_int,
    set_variant,
)


def add(sub: Any) -> None:
    """Add the ``render`` subcommand to the subparsers ``sub``."""
    p = sub.add_parser(
        "render",
        help="render a scene (default: the built-in Cornell box) to EXR + PNG",
        description="Render SCENE.xml (or the built-in Cornell box) in passes and write an EXR with render "
        "metadata plus an sRGB PNG preview. Ctrl-C or the --time budget writes the average of the finished "
        "passes.",
    )
    p.add_argument("scene", nargs="?", help="Mitsuba scene file (default: mi.cornell_box())")
    p.add_argument(
        "-i", "--integrator", metavar="NAME",
        help=f"integrator plugin (default: {DEFAULT_INTEGRATOR}); 'scene' uses the scene's own integrator",
    )
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--spp", type=positive_int, metavar="N",
                        help="samples per pixel (default: the scene sampler's sample count)")
    budget.add_argument("--time", type=positive_float, metavar="SECONDS",
                        help="render passes until this time budget is used up")
    p.add_argument("--passes", type=positive_int, metavar="N", help="split --spp into N passes")
    p.add_argument("--pass-spp", type=positive_int, metavar="N", help="at most N samples per pixel per pass")
    p.add_argument("-o", "--out", metavar="OUT.exr",
                   help="output EXR; a PNG preview is written next to it (default: out/<scene>_<integrator>.exr)")
    p.add_argument("-D", dest="defines", action="append", type=key_value, default=[], metavar="NAME=VALUE",
                   help="scene parameter ($NAME in the scene file), repeatable")
    p.add_argument("-p", "--param", dest="params", action="append", type=key_value, default=[],
                   metavar="KEY=VALUE", help="integrator property (int, float, true/false, text), repeatable")
    p.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default: {DEFAULT_VARIANT})")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the first pass (default: 0)")
    p.add_argument("--res", type=resolution, metavar="W[xH]",
                   help=f"image size of the built-in scene (default: {DEFAULT_RES})")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="exposure of the PNG preview")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    cluster = p.add_mutually_exclusive_group()
    cluster.add_argument("--workers", type=positive_int, metavar="N",
                         help="render the passes on a local Dask cluster of N worker processes (each with "
                         "cores/N Dr.Jit threads, at least 2); needs segmitsuba[distributed]")
    cluster.add_argument("--scheduler", metavar="ADDRESS",
                         help="render the passes on the Dask cluster at ADDRESS (tcp://host:8786, or a scheduler "
                         "file .json); the scene and its files are shipped to the workers")
    p.set_defaults(func=run)


def _render_distributed(args: argparse.Namespace, name: str) -> Any:
    """The render of :func:`run` on a Dask cluster (the scene and integrator were checked locally)."""
    from ..distributed import package_scene, render_distributed

    scene: Any = builtin_scene(args.res) if args.scene is None else args.scene
    try:
        bundle = package_scene(scene, dict(args.defines))
    except (OSError, ValueError, TypeError) as e:
        raise CliError(f"cannot ship the scene to the workers: {e}") from None
    integrator = None if args.integrator == "scene" else {"type": name, **{k: parse_value(v) for k, v in args.params}}
    try:
        return render_distributed(bundle, integrator, spp=args.spp, time_budget=args.time, passes=args.passes,
                                  pass_spp=args.pass_spp, seed=args.seed, scheduler=args.scheduler,
                                  workers=args.workers, variant=args.variant, progress=not args.quiet)
    except ConnectionError as e:
        raise CliError(str(e)) from None


def run(args: argparse.Namespace) -> int:
    """``segmitsuba render``; returns the exit code (130 when interrupted after a finished pass)."""
    from ..imageio import write_exr, write_png
    from ..rendering import environment, render_passes  # looked up per call: tests replace render_passes

    if args.passes is not None and args.time is not None:
        raise CliError("--passes needs --spp (with --time the pass sizes adapt to the budget)")
    say = progress_printer(args.quiet)

    distributed = getattr(args, "workers", None) is not None or getattr(args, "scheduler", None) is not None
    if distributed:
        from ..distributed import INSTALL_HINT, require_distributed

        try:
            require_distributed()
        except ImportError:
            raise CliError(f"--workers/--scheduler need Dask's distributed package: {INSTALL_HINT}") from None
    if args.out is not None:
        check_output(Path(args.out))  # early, so a bad path fails before loading anything
    set_variant(args.variant)
    scene, scene_name = load_scene(args.scene, dict(args.defines), args.res)
    integrator, name = make_integrator(scene, args.integrator, {k: parse_value(v) for k, v in args.params})
    stem = "cornell_box" if args.scene is None else Path(args.scene).stem
    out = Path(args.out) if args.out is not None else Path("out") / f"{stem}_{name.replace(':', '_')}.exr"
    check_output(out)

    film = scene.sensors()[0].film()
    size = film.crop_size()
    scene_spp = int(scene.sensors()[0].sampler().sample_count())
    budget = f"{args.time:g} s budget" if args.time else f"{args.spp} spp" if args.spp else f"{scene_spp} spp (scene)"
    say(f"rendering {scene_name} ({int(size[0])}x{int(size[1])}) with {integrator}, {budget}, "
        f"variant {args.variant}, seed {args.seed}")

    try:
        if distributed:
            result = _render_distributed(args, name)
        else:
            result = render_passes(scene, integrator, spp=args.spp, time_budget=args.time, passes=args.passes,
                                   pass_spp=args.pass_spp, seed=args.seed, progress=not args.quiet)
    except KeyboardInterrupt:
        raise CliError("interrupted before the first pass finished; nothing written", EXIT_INTERRUPTED) from None
    except CliError:
        raise
    except Exception as e:
        raise CliError(f"render failed: {mitsuba_message(e)}", EXIT_FAILURE) from None

    if result.interrupted:
        say(f"interrupted: writing the average of the {result.passes} finished passes ({result.spp} spp)")
    elif result.stop_reason == "time":
        say(f"time budget reached: {result.passes} passes, {result.spp} spp in {result.seconds:.1f} s")

    metadata: dict[str, Any] = {
        "software": f"segmitsuba {__version__}",
        "capDate": time.strftime("%Y:%m:%d %H:%M:%S"),
        "integrator": name,
        "integrator_params": {k: parse_value(v) for k, v in args.params},
        "integrator_description": str(integrator),
        "spp": result.spp,
        "passes": result.passes,
        "pass_spp": result.pass_spp,
        "pass_seconds": [round(t, 4) for t in result.pass_seconds],
        "render_time": round(result.seconds, 4),
        "stop_reason": result.stop_reason,
        "interrupted": result.interrupted,
        "seed": args.seed,
        "pass_seeds": result.seeds,
        "scene": scene_name,
        "defines": dict(args.defines),
        "command": " ".join(["segmitsuba", *sys.argv[1:]]),
    }
    if args.time is not None:
        metadata["time_budget"] = args.time
    metadata.update(environment())
    if distributed:
        metadata.update({
            "dask_scheduler": result.scheduler,
            "dask_workers": result.workers,
            "tasks": len(result.task_passes),
            "task_passes": result.task_passes,
            "task_workers": result.task_workers,
            "cancelled_tasks": result.cancelled_tasks,
            "worker_environment": result.worker_environment,
        })

    png = out.with_suffix(".png")
    try:
        write_exr(out, result.image, result.channels, metadata)
        write_png(png, result.image, exposure=args.exposure)
    except Exception as e:
        raise CliError(f"cannot write the result: {mitsuba_message(e)}", EXIT_FAILURE) from None
    print(f"wrote {out} ({', '.join(result.channels)}; {result.spp} spp, {result.passes} "
          f"pass{'es' if result.passes != 1 else ''}, {result.seconds:.1f} s)")
    print(f"wrote {png}")
    sys.stdout.flush()
    return EXIT_INTERRUPTED if result.interrupted else 0
