"""``segmitsuba reference``: render the converged references of the test scenes (:mod:`segmitsuba.references`)
and write them as EXR files with metadata."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .. import references
from ..references import DEFAULT_MAX_DEPTH, DEFAULT_RES, DEFAULT_SEED, EXCLUDED, REFERENCES_DIR
from .common import DEFAULT_VARIANT, EXIT_FAILURE, CliError, check_max_depth, mitsuba_message, positive_int, set_variant


def add(sub: Any) -> None:
    """Add the ``reference`` subcommand to the subparsers ``sub``."""
    p = sub.add_parser(
        "reference", help="render converged references of the test scenes",
        description="Render converged reference images of scenes/*.xml (path, or ptracer where path is "
        "incomplete) in two independent halves, and write their average as EXR with metadata (method, spp, "
        "seeds, time, scene sha256, half_relmse) to tests/references/<scene>_r<res>_d<depth>.exr.",
    )
    p.add_argument("scenes", nargs="*", metavar="SCENE", help="scene names (cornell, cornell.xml, scenes/cornell.xml)")
    p.add_argument("--all", action="store_true", help=f"every scene in scenes/ except {', '.join(sorted(EXCLUDED))}")
    p.add_argument("--res", type=positive_int, default=DEFAULT_RES, help=f"image side (default {DEFAULT_RES})")
    p.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH,
                   help=f"max_depth of the integrator (default {DEFAULT_MAX_DEPTH})")
    p.add_argument("--spp", type=positive_int, help="total spp over both halves (default: per scene, see SPP)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"seed of the first half (default {DEFAULT_SEED})")
    p.add_argument("--dir", type=Path, default=REFERENCES_DIR, help="output folder (default: tests/references)")
    p.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default {DEFAULT_VARIANT})")
    p.set_defaults(func=run)


def select_scenes(names: Sequence[str], everything: bool) -> list[str]:
    """The scene stems to render: ``names`` (each a scene with a reference, duplicates dropped) or, with
    ``everything`` (--all), every reference scene."""
    available = references.reference_scenes()
    if everything and names:
        raise CliError("give SCENE names or --all, not both")
    if everything:
        return available
    if not names:
        raise CliError("name the scenes to render, or --all (scenes: " + ", ".join(available) + ")")
    stems = []
    for name in names:
        stem = references.scene_stem(name)
        if stem in EXCLUDED:
            raise CliError(f"scene '{stem}' has no reference: {EXCLUDED[stem]}")
        if not references.scene_file(stem).is_file():
            raise CliError(f"unknown scene '{name}' (scenes: {', '.join(available)})")
        stems.append(stem)
    return list(dict.fromkeys(stems))


def run(args: argparse.Namespace) -> int:
    """``segmitsuba reference``: one :func:`segmitsuba.references.make_reference` per selected scene."""
    stems = select_scenes(args.scenes, args.all)
    if args.spp is not None and args.spp < 2:
        raise CliError("--spp must be at least 2 (two halves)")
    check_max_depth(args.max_depth)
    set_variant(args.variant)
    start = time.perf_counter()
    for stem in stems:
        try:
            out = references.make_reference(stem, args.res, args.max_depth, args.spp, args.seed, args.dir,
                                            say=lambda m: print(m, flush=True))
        except KeyboardInterrupt:
            raise
        except Exception as e:
            raise CliError(f"reference for '{stem}' failed: {mitsuba_message(e)}", EXIT_FAILURE) from None
        print(f"wrote {out}", flush=True)
    if len(stems) > 1:
        print(f"{len(stems)} references in {time.perf_counter() - start:.1f} s", flush=True)
    sys.stdout.flush()
    return 0
