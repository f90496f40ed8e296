"""The ``segmitsuba`` command: ``render``, ``info`` and ``bench`` (also ``python -m segmitsuba``).

Subcommands are argparse subparsers registered in :data:`COMMANDS`: a new one (e.g. ``compare``) is a function
``add(subparsers)`` that adds its parser and sets ``func`` (``args -> exit code``) as its default.

Errors are one line on stderr without a traceback: exit code 2 for usage and input errors (bad arguments,
scene, integrator or output path), 1 when rendering or writing fails, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

import segmitsuba  # first: configures libLLVM before drjit is imported

#: integrator used when ``--integrator`` is not given
DEFAULT_INTEGRATOR = "segment_bdf"
DEFAULT_VARIANT = "llvm_ad_rgb"
#: side of the built-in Cornell box image unless --res says otherwise
DEFAULT_RES = 256
BUILTIN_SCENE = "builtin:cornell_box"

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class CliError(Exception):
    """An error reported as one line, with the process exit code."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (argparse prints the whole usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _err(message: str) -> None:
    print(f"segmitsuba: {message}", file=sys.stderr, flush=True)


def mitsuba_message(exc: BaseException, max_chars: int = 500) -> str:
    """Mitsuba's error text on one line, without its ``[file.cpp:123]`` source locations."""
    text = str(exc)
    if "Traceback (most recent call last):" in text:
        # a Python plugin raised inside Mitsuba's parser: its own message (last unindented line) says it all
        tail = text.rsplit("Traceback (most recent call last):", 1)[1]
        lines = [ln for ln in tail.splitlines() if ln.strip() and not ln[0].isspace()]
        if lines:
            text = re.sub(r"^\w+(?:Error|Exception|Warning)?:\s*", "", "\n".join(lines))
    text = re.sub(r"\[[\w./\\-]+\.(?:cpp|h|py):\d+\]\s*", "", text)
    text = " ".join(line.strip() for line in text.splitlines() if line.strip()) or type(exc).__name__
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."


# --- argument types ------------------------------------------------------------------------------------


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def seed_int(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^32), got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^32), got {text!r}")
    return value


def resolution(text: str) -> tuple[int, int]:
    """``256`` or ``320x240`` (width x height)."""
    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*", text)
    if not m or int(m.group(1)) < 1 or (m.group(2) is not None and int(m.group(2)) < 1):
        raise argparse.ArgumentTypeError(f"expected SIZE or WIDTHxHEIGHT (positive), got {text!r}")
    w = int(m.group(1))
    return w, int(m.group(2)) if m.group(2) else w


def key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return key.strip(), value


def parse_value(text: str) -> bool | int | float | str:
    """An integrator property from the command line: bool (true/false), int, float, else the string."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


# --- render --------------------------------------------------------------------------------------------


def _add_render(sub: Any) -> None:
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
    p.set_defaults(func=cmd_render)


def _check_output(out: Path) -> None:
    """Fail before rendering if the result cannot be written."""
    if out.suffix.lower() != ".exr":
        raise CliError(f"--out must name an .exr file, got '{out}'")
    if out.is_dir():
        raise CliError(f"--out '{out}' is a directory")
    parent = out.parent if str(out.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise CliError(f"cannot create output directory '{parent}': a file is in the way") from None
    except OSError as e:
        raise CliError(f"cannot create output directory '{parent}': {e.strerror or e}") from None
    try:  # a real probe: os.access says yes to root even where writing fails (read-only mounts, /proc)
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".segmitsuba-probe-"):
            pass
    except OSError as e:
        raise CliError(f"output directory '{parent}' is not writable: {e.strerror or e}") from None
    for path in (out, out.with_suffix(".png")):
        if path.exists() and not os.access(path, os.W_OK):
            raise CliError(f"output file '{path}' is not writable")


def _set_variant(variant: str) -> None:
    import mitsuba as mi

    if variant not in mi.variants():
        raise CliError(f"unknown Mitsuba variant '{variant}' (available: {', '.join(mi.variants())})")
    try:
        mi.set_variant(variant)
    except Exception as e:  # registration of segmitsuba's integrators failed
        raise CliError(f"cannot set variant '{variant}': {mitsuba_message(e)}", EXIT_FAILURE) from None


def _load_scene(args: argparse.Namespace) -> tuple[Any, str]:
    """The scene and how the metadata names it."""
    import mitsuba as mi

    if args.scene is None:
        if args.defines:
            raise CliError("-D defines need a scene file (the built-in scene has no parameters; use --res)")
        scene = mi.cornell_box()
        w, h = args.res or (DEFAULT_RES, DEFAULT_RES)
        scene["sensor"]["film"]["width"], scene["sensor"]["film"]["height"] = w, h
        return mi.load_dict(scene), BUILTIN_SCENE
    if args.res is not None:
        raise CliError("--res only applies to the built-in scene; give scene files their size with -D")
    path = Path(args.scene)
    if not path.exists():
        raise CliError(f"scene file '{path}' does not exist")
    if not path.is_file():
        raise CliError(f"scene '{path}' is not a file")
    try:
        with open(path, "rb") as f:
            f.read(1)
    except OSError as e:
        raise CliError(f"cannot read scene file '{path}': {e.strerror or e}") from None
    try:
        scene = mi.load_file(str(path), **dict(args.defines))
    except Exception as e:
        raise CliError(f"cannot load scene '{path}': {mitsuba_message(e)}") from None
    return scene, str(path.resolve())


def _make_integrator(scene: Any, args: argparse.Namespace, say: Callable[[str], None]) -> tuple[Any, str]:
    """The integrator to render with, and its plugin name."""
    import mitsuba as mi

    params = {k: parse_value(v) for k, v in args.params}
    if args.integrator == "scene":
        if params:
            raise CliError("--param needs an explicit --integrator (not 'scene')")
        integrator = scene.integrator()
        return integrator, f"scene:{integrator.class_name()}"

    def load(name: str) -> Any:
        return mi.load_dict({"type": name, **params})

    name = args.integrator or DEFAULT_INTEGRATOR
    try:
        integrator = load(name)
    except Exception as e:
        if _not_found(e, name):
            ours = ", ".join(segmitsuba.INTEGRATORS)
            raise CliError(
                f"unknown integrator '{name}' (segmitsuba: {ours}; or a Mitsuba integrator such as path, "
                "volpath, ptracer)"
            ) from None
        raise CliError(f"cannot create integrator '{name}' {_format_params(params)}: {mitsuba_message(e)}") from None
    if not isinstance(integrator, mi.Integrator):
        raise CliError(f"'{name}' is a {type(integrator).__name__} plugin, not an integrator")
    return integrator, name


def _not_found(exc: BaseException, name: str) -> bool:
    return f'Plugin "{name}" not found' in str(exc)


def _format_params(params: dict[str, Any]) -> str:
    return "(" + ", ".join(f"{k}={v}" for k, v in params.items()) + ")" if params else "(default properties)"


def _render_distributed(args: argparse.Namespace, name: str) -> Any:
    """The render of ``cmd_render`` on a Dask cluster (the scene and integrator were checked locally)."""
    import mitsuba as mi

    from .distributed import package_scene, render_distributed

    if args.scene is None:
        scene: Any = mi.cornell_box()
        w, h = args.res or (DEFAULT_RES, DEFAULT_RES)
        scene["sensor"]["film"]["width"], scene["sensor"]["film"]["height"] = w, h
    else:
        scene = args.scene
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


def cmd_render(args: argparse.Namespace) -> int:
    from .imageio import write_exr, write_png
    from .rendering import environment, render_passes

    if args.passes is not None and args.time is not None:
        raise CliError("--passes needs --spp (with --time the pass sizes adapt to the budget)")
    say = (lambda _m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))

    distributed = getattr(args, "workers", None) is not None or getattr(args, "scheduler", None) is not None
    if distributed:
        from .distributed import INSTALL_HINT, require_distributed

        try:
            require_distributed()
        except ImportError:
            raise CliError(f"--workers/--scheduler need Dask's distributed package: {INSTALL_HINT}") from None
    if args.out is not None:
        _check_output(Path(args.out))  # early, so a bad path fails before loading anything
    _set_variant(args.variant)
    scene, scene_name = _load_scene(args)
    integrator, name = _make_integrator(scene, args, say)
    stem = "cornell_box" if args.scene is None else Path(args.scene).stem
    out = Path(args.out) if args.out is not None else Path("out") / f"{stem}_{name.replace(':', '_')}.exr"
    _check_output(out)

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
        "software": f"segmitsuba {segmitsuba.__version__}",
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


# --- info ----------------------------------------------------------------------------------------------


def _add_info(sub: Any) -> None:
    p = sub.add_parser("info", help="show variants, libLLVM, threads, versions and integrators",
                       description="Show the Mitsuba variants, the libLLVM that Dr.Jit loaded, the thread count, "
                       "package versions and segmitsuba's integrators.")
    p.add_argument("--variant", default=DEFAULT_VARIANT, help="variant to register the integrators for")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)


def cmd_info(args: argparse.Namespace) -> int:
    import mitsuba as mi

    from .rendering import environment

    variant_error = ""
    try:
        _set_variant(args.variant)
    except CliError as e:
        if e.code == EXIT_USAGE:
            raise
        variant_error = str(e)
    registered = []
    if mi.variant():
        for name in dict.fromkeys([*segmitsuba.INTEGRATORS, DEFAULT_INTEGRATOR]):
            try:
                mi.load_dict({"type": name})
                registered.append(name)
            except Exception:
                pass
    info: dict[str, Any] = {
        "variants": list(mi.variants()),
        **environment(),
        "integrators": list(segmitsuba.INTEGRATORS),
        "integrators_loadable": [n for n in registered if n in segmitsuba.INTEGRATORS],
        "default_integrator": DEFAULT_INTEGRATOR,
    }
    try:
        import numpy
        import OpenEXR

        info["numpy_version"] = numpy.__version__
        info["openexr_version"] = getattr(OpenEXR, "__version__", "?")
    except ImportError:
        pass
    if variant_error:
        info["error"] = variant_error
    if args.json:
        print(json.dumps(info, indent=2))
        return 0 if not variant_error else EXIT_FAILURE
    rows = [
        ("variants", ", ".join(info["variants"])),
        ("variant", info["variant"] or "(none)"),
        ("libLLVM", f"{info.get('llvm_version', 'not loaded')} ({info['libllvm_path'] or 'system default'})"),
        ("threads", str(info["threads"])),
        ("segmitsuba", info["segmitsuba_version"]),
        ("mitsuba", info["mitsuba_version"]),
        ("drjit", info["drjit_version"]),
        ("numpy", info.get("numpy_version", "?")),
        ("OpenEXR", info.get("openexr_version", "?")),
        ("python", info["python_version"]),
        ("integrators", ", ".join(f"{n}{'' if n in registered else ' (not loadable)'}"
                                  for n in info["integrators"])),
        ("default", DEFAULT_INTEGRATOR),
    ]
    if variant_error:
        rows.append(("error", variant_error))
    width = max(len(k) for k, _ in rows)
    print("\n".join(f"{k:<{width}}  {v}" for k, v in rows))
    return 0 if not variant_error else EXIT_FAILURE


# --- bench ---------------------------------------------------------------------------------------------


def _add_bench(sub: Any) -> None:
    p = sub.add_parser(
        "bench", help="run benchmarks from segmitsuba/benchmarks and print their tables",
        description="Run the named benchmarks (default: all) from segmitsuba.benchmarks. Arguments after the "
        "names are passed to each benchmark, e.g. 'segmitsuba bench grid --n 100000'.",
    )
    p.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    p.add_argument("argv", nargs=argparse.REMAINDER, metavar="[NAME ...] [ARGS]")
    p.set_defaults(func=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    from . import benchmarks

    found = benchmarks.available()
    if args.list:
        print("\n".join(found) if found else "(no benchmarks)")
        return 0
    argv = list(args.argv)
    if argv and argv[0] == "--":
        argv = argv[1:]
    names: list[str] = []
    while argv and not argv[0].startswith("-"):
        if argv[0] not in found:
            if names:  # a value for the benchmarks, not a name
                break
            raise CliError(f"unknown benchmark '{argv[0]}' (available: {', '.join(found) or 'none'})")
        names.append(argv.pop(0))
    if argv and argv[0] == "--":
        argv = argv[1:]
    for name in names or found:
        if len(names or found) > 1:
            print(f"== {name} ==", flush=True)
        try:
            table = benchmarks.run(name, argv)
        except (SystemExit, KeyboardInterrupt, CliError):
            raise
        except Exception as e:
            raise CliError(f"benchmark '{name}' failed: {mitsuba_message(e)}", EXIT_FAILURE) from None
        print(table, flush=True)
    return 0


# --- entry point ---------------------------------------------------------------------------------------

#: subcommands, in help order; each adds its parser to the subparsers object and sets ``func``
COMMANDS: list[Callable[[Any], None]] = [_add_render, _add_info, _add_bench]


def _add_reference(sub: Any) -> None:
    from .references import add  # imported here: segmitsuba.references imports this module

    add(sub)


COMMANDS.append(_add_reference)


def _add_compare(sub: Any) -> None:
    from .compare import add  # imported here: segmitsuba.compare imports this module

    add(sub)


COMMANDS.append(_add_compare)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="segmitsuba",
        description="Segment-based light transport for Mitsuba 3.",
        epilog="Run 'segmitsuba COMMAND --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"segmitsuba {segmitsuba.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for add in COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code (the console script exits with it)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as e:
        _err(f"error: {e}")
        return e.code
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
