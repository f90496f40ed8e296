"""Benchmarks run by ``segmitsuba bench``.

Every module in this package is a benchmark named after the module, with hyphens for underscores (module
``equal_time`` is the benchmark ``equal-time``). It exposes ``run(args: list[str] | None = None) -> str``,
which parses its own ``args`` (e.g. with argparse), does the work and returns a printable table. Modules whose
name starts with ``_`` are helpers, not benchmarks.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType


def module_name(name: str) -> str:
    """The module of benchmark ``name``: hyphens become underscores (``equal-time`` -> ``equal_time``)."""
    return name.replace("-", "_")


def available() -> list[str]:
    """Names of the benchmarks in this package (module names with hyphens for underscores), sorted."""
    return sorted(m.name.replace("_", "-") for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def load(name: str) -> ModuleType:
    """Import benchmark ``name`` (or its module name); ValueError if there is none, or if it has no ``run``."""
    if module_name(name) not in {module_name(n) for n in available()}:
        raise ValueError(f"unknown benchmark {name!r} (available: {', '.join(available()) or 'none'})")
    module = importlib.import_module(f"{__name__}.{module_name(name)}")
    if not callable(getattr(module, "run", None)):
        raise ValueError(f"benchmark module {module.__name__} has no run(args) function")
    return module


def run(name: str, args: list[str] | None = None) -> str:
    """Run benchmark ``name`` with its command-line ``args`` and return its table."""
    return str(load(name).run(args))
