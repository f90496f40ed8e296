"""``segmitsuba bench``: run benchmarks from :mod:`segmitsuba.benchmarks` by name and print their tables."""

from __future__ import annotations

import argparse
from typing import Any

from .common import EXIT_FAILURE, CliError, mitsuba_message


def add(sub: Any) -> None:
    """Add the ``bench`` subcommand to the subparsers ``sub``."""
    p = sub.add_parser(
        "bench", help="run benchmarks from segmitsuba/benchmarks and print their tables",
        description="Run the named benchmarks (default: all) from segmitsuba.benchmarks. Arguments after the "
        "names are passed to each benchmark, e.g. 'segmitsuba bench grid --n 100000'.",
    )
    p.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    p.add_argument("argv", nargs=argparse.REMAINDER, metavar="[NAME ...] [ARGS]")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``segmitsuba bench``: the leading words that name benchmarks select them; the rest goes to each."""
    from .. import benchmarks

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
