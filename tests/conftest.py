"""Shared fixtures: the JIT variant, the scenes folder and statistical helpers."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi  # noqa: E402, I001
import pytest

import segmitsuba  # noqa: F401  (sets the libLLVM path before drjit is imported)

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"


def error_chain(exc: BaseException | None) -> str:
    """An exception's message and those of its causes (Mitsuba wraps plugin errors), joined by ' | '."""
    parts = []
    while exc is not None:
        parts.append(str(exc))
        exc = exc.__cause__
    return " | ".join(parts)


@pytest.fixture(autouse=True)
def llvm_variant():
    """Every test starts in llvm_ad_rgb unless it switches itself (and is restored afterwards)."""
    mi.set_variant("llvm_ad_rgb")
    yield
    mi.set_variant("llvm_ad_rgb")
