"""Shared fixtures: the JIT variant, the scenes folder and statistical helpers."""

from __future__ import annotations

import signal
from pathlib import Path

import mitsuba as mi  # noqa: E402, I001
import pytest

import segmitsuba  # noqa: F401  (sets the libLLVM path before drjit is imported)

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"


def lattice_budget(scene: mi.Scene, groups: int) -> float:
    """A ``memory_budget`` (MiB) under which segment_bdf splits one sample per pixel into ``groups`` film lattices."""
    from segmitsuba.film import film_sample_count

    probe = mi.load_dict({"type": "segment_bdf"})
    pixels = film_sample_count(scene.sensors()[0].film())
    per_sample = probe._bytes_per_sample(probe.next_event_for(scene, pixels), probe.light_ratio_for(scene))
    return pixels * per_sample / (groups - 0.5) / 2**20


def small_cornell(res: int = 16) -> dict:
    """Mitsuba's Cornell box (a scene dict) on a ``res`` x ``res`` film."""
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = res
    return d


def error_chain(exc: BaseException | None) -> str:
    """An exception's message and those of its causes (Mitsuba wraps plugin errors), joined by ' | '."""
    parts = []
    while exc is not None:
        parts.append(str(exc))
        exc = exc.__cause__
    return " | ".join(parts)


def default_sigint() -> None:
    """``preexec_fn`` of a subprocess a test interrupts: SIGINT back to its default, since a child inherits an
    ignored SIGINT (pytest started in the background by a non-interactive shell, ``cmd &``) and would never see it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(autouse=True)
def llvm_variant():
    """Every test starts in llvm_ad_rgb unless it switches itself (and is restored afterwards)."""
    mi.set_variant("llvm_ad_rgb")
    yield
    mi.set_variant("llvm_ad_rgb")
