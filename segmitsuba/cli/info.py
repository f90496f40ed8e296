"""``segmitsuba info``: the Mitsuba variants, the libLLVM that Dr.Jit loaded, the thread count, package versions
and segmitsuba's integrators, as a table or JSON."""

from __future__ import annotations

import argparse
import json
from typing import Any

from .. import INTEGRATORS
from .common import DEFAULT_INTEGRATOR, DEFAULT_VARIANT, EXIT_FAILURE, EXIT_USAGE, CliError, set_variant


def add(sub: Any) -> None:
    """Add the ``info`` subcommand to the subparsers ``sub``."""
    p = sub.add_parser("info", help="show variants, libLLVM, threads, versions and integrators",
                       description="Show the Mitsuba variants, the libLLVM that Dr.Jit loaded, the thread count, "
                       "package versions and segmitsuba's integrators.")
    p.add_argument("--variant", default=DEFAULT_VARIANT, help="variant to register the integrators for")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``segmitsuba info``; exit code 1 (after printing what is known) when the variant cannot be set."""
    import mitsuba as mi

    from ..rendering import environment

    variant_error = ""
    try:
        set_variant(args.variant)
    except CliError as e:
        if e.code == EXIT_USAGE:
            raise
        variant_error = str(e)
    registered = []
    if mi.variant():
        for name in dict.fromkeys([*INTEGRATORS, DEFAULT_INTEGRATOR]):
            try:
                mi.load_dict({"type": name})
                registered.append(name)
            except Exception:
                pass
    info: dict[str, Any] = {
        "variants": list(mi.variants()),
        **environment(),
        "integrators": list(INTEGRATORS),
        "integrators_loadable": [n for n in registered if n in INTEGRATORS],
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
