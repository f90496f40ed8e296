"""What the ``segmitsuba`` commands share: the error type and exit codes, argument types, Mitsuba's error text
on one line, setting the variant, loading scenes, creating integrators and checking output paths."""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .. import INTEGRATORS  # the package first: it configures libLLVM before drjit is imported

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


def err(message: str) -> None:
    """One line on stderr, prefixed with the program name."""
    print(f"segmitsuba: {message}", file=sys.stderr, flush=True)


def progress_printer(quiet: bool) -> Callable[[str], None]:
    """Where a command's progress lines go: stderr (stdout holds the results), or nowhere with --quiet."""
    if quiet:
        return lambda _m: None
    return lambda m: print(m, file=sys.stderr, flush=True)


def mitsuba_message(exc: BaseException, max_chars: int = 500) -> str:
    """Mitsuba's error text on one line, without its ``[file.cpp:123]`` source locations. Where Dr.Jit wraps an
    error raised inside ``mi.render`` ("... custom differentiable operation. (see above)"), the error it wraps."""
    while "(see above)" in str(exc) and exc.__cause__ is not None:
        exc = exc.__cause__
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


def check_max_depth(max_depth: int) -> None:
    """``--max-depth``: -1 (unbounded) or positive, as Mitsuba's integrators take it."""
    if max_depth == 0 or max_depth < -1:
        raise CliError(f"--max-depth must be -1 (unbounded) or positive, got {max_depth}")


# --- Mitsuba: variant, scenes, integrators -------------------------------------------------------------


def set_variant(variant: str) -> None:
    import mitsuba as mi

    if variant not in mi.variants():
        raise CliError(f"unknown Mitsuba variant '{variant}' (available: {', '.join(mi.variants())})")
    try:
        mi.set_variant(variant)
    except Exception as e:  # registration of segmitsuba's integrators failed
        raise CliError(f"cannot set variant '{variant}': {mitsuba_message(e)}", EXIT_FAILURE) from None


def builtin_scene(res: tuple[int, int] | None) -> dict[str, Any]:
    """The built-in Cornell box as a scene dict, ``res`` (width, height) or :data:`DEFAULT_RES` square."""
    import mitsuba as mi

    scene = mi.cornell_box()
    w, h = res or (DEFAULT_RES, DEFAULT_RES)
    scene["sensor"]["film"]["width"], scene["sensor"]["film"]["height"] = w, h
    return scene


def load_scene(scene_file: str | None, defines: dict[str, str], res: tuple[int, int] | None) -> tuple[Any, str]:
    """The scene (``scene_file`` with its $-parameters ``defines``, or the built-in one at ``res``) and how the
    metadata names it."""
    import mitsuba as mi

    if scene_file is None:
        if defines:
            raise CliError("-D defines need a scene file (the built-in scene has no parameters; use --res)")
        return mi.load_dict(builtin_scene(res)), BUILTIN_SCENE
    if res is not None:
        raise CliError("--res only applies to the built-in scene; give scene files their size with -D")
    path = Path(scene_file)
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
        scene = mi.load_file(str(path), **defines)
    except Exception as e:
        raise CliError(f"cannot load scene '{path}': {mitsuba_message(e)}") from None
    return scene, str(path.resolve())


def plugin_not_found(exc: BaseException, name: str) -> bool:
    """Whether Mitsuba's error ``exc`` says that no plugin is called ``name``."""
    return f'Plugin "{name}" not found' in str(exc)


def format_params(params: dict[str, Any]) -> str:
    return "(" + ", ".join(f"{k}={v}" for k, v in params.items()) + ")" if params else "(default properties)"


def make_integrator(scene: Any, name: str | None, params: dict[str, Any]) -> tuple[Any, str]:
    """The integrator to render with, and its plugin name: ``name`` (default :data:`DEFAULT_INTEGRATOR`)
    with properties ``params``, or the scene's own for ``name == 'scene'``."""
    import mitsuba as mi

    if name == "scene":
        if params:
            raise CliError("--param needs an explicit --integrator (not 'scene')")
        integrator = scene.integrator()
        return integrator, f"scene:{integrator.class_name()}"

    name = name or DEFAULT_INTEGRATOR
    try:
        integrator = mi.load_dict({"type": name, **params})
    except Exception as e:
        if plugin_not_found(e, name):
            ours = ", ".join(INTEGRATORS)
            raise CliError(
                f"unknown integrator '{name}' (segmitsuba: {ours}; or a Mitsuba integrator such as path, "
                "volpath, ptracer)"
            ) from None
        raise CliError(f"cannot create integrator '{name}' {format_params(params)}: {mitsuba_message(e)}") from None
    if not isinstance(integrator, mi.Integrator):
        raise CliError(f"'{name}' is a {type(integrator).__name__} plugin, not an integrator")
    return integrator, name


# --- outputs -------------------------------------------------------------------------------------------


def check_output(out: Path) -> None:
    """Fail before rendering if the EXR ``out`` (and the PNG next to it) cannot be written."""
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


def prepare_out_dir(out: Path) -> None:
    """Create the output folder ``out`` and fail before rendering if it cannot be written to."""
    if out.exists() and not out.is_dir():
        raise CliError(f"--out '{out}' is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".segmitsuba-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise CliError(f"output folder '{out}' is not writable: {e.strerror or e}") from None
