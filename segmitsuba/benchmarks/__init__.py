"""Benchmarks run by ``segmitsuba bench``.

Every module in this package is a benchmark named after the module. It exposes
``run(args: list[str] | None = None) -> str``, which parses its own ``args`` (e.g. with argparse), does the
work and returns a printable table. Modules whose name starts with ``_`` are helpers, not benchmarks.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType


def available() -> list[str]:
    """Names of the benchmark modules in this package, sorted."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def load(name: str) -> ModuleType:
    """Import benchmark ``name``; ValueError if there is none, or if it has no ``run``."""
    if name not in available():
        raise ValueError(f"unknown benchmark {name!r} (available: {', '.join(available()) or 'none'})")
    module = importlib.import_module(f"{__name__}.{name}")
    if not callable(getattr(module, "run", None)):
        raise ValueError(f"benchmark module {module.__name__} has no run(args) function")
    return module


def run(name: str, args: list[str] | None = None) -> str:
    """Run benchmark ``name`` with its command-line ``args`` and return its table."""
    return str(load(name).run(args))
