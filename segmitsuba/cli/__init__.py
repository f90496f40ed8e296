"""The ``segmitsuba`` command: ``render``, ``info``, ``bench``, ``reference`` and ``compare`` (also
``python -m segmitsuba``).

Each command is a module of this package with ``add(subparsers)``, which adds its parser and sets ``func``
(``args -> exit code``) as its default, and ``run(args)``; :data:`COMMANDS` lists the ``add`` functions in help
order. What more than one command uses is in :mod:`segmitsuba.cli.common`.

Errors are one line on stderr without a traceback: exit code 2 for usage and input errors (bad arguments,
scene, integrator or output path), 1 when rendering or writing fails, 130 when interrupted.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from .. import __version__
from . import bench, compare, info, reference, render
from .common import (
    BUILTIN_SCENE,
    DEFAULT_INTEGRATOR,
    DEFAULT_RES,
    DEFAULT_VARIANT,
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    CliError,
    err,
)

__all__ = ["BUILTIN_SCENE", "COMMANDS", "DEFAULT_INTEGRATOR", "DEFAULT_RES", "DEFAULT_VARIANT", "EXIT_FAILURE",
           "EXIT_INTERRUPTED", "EXIT_USAGE", "CliError", "build_parser", "main"]

#: subcommands, in help order; each adds its parser to the subparsers object and sets ``func``
COMMANDS: list[Callable[[Any], None]] = [render.add, info.add, bench.add, reference.add, compare.add]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (argparse prints the whole usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``segmitsuba`` parser with every command of :data:`COMMANDS`."""
    parser = _Parser(
        prog="segmitsuba",
        description="Segment-based light transport for Mitsuba 3.",
        epilog="Run 'segmitsuba COMMAND --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"segmitsuba {__version__}")
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
        err(f"error: {e}")
        return e.code
    except KeyboardInterrupt:
        err("interrupted")
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return EXIT_FAILURE
