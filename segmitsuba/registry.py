"""Registration of segmitsuba's integrators with Mitsuba, per variant.

``mi.register_integrator`` applies to the current variant only, and an integrator class must derive from that
variant's ``mi.SamplingIntegrator``. So, like Mitsuba's own Python integrators, each integrator module is
(re)imported whenever the variant changes; importing it defines its class and registers it.
"""

from __future__ import annotations

import importlib
import sys

import mitsuba as mi

#: plugin name -> module under ``segmitsuba.integrators`` that defines it
INTEGRATORS: dict[str, str] = {
    "segment_pt": "segment_pt",
    "segment_lt": "segment_lt",
    "segment_bdpt": "segment_bdpt",
    "segment_mvf": "segment_mvf",
    "segment_pf": "segment_pf",
    "segment_bdf": "segment_bdf",
}
#: modules defining shared base classes, re-imported first on a variant change
_BASES = ("segmitsuba.integrators.base", "segmitsuba.integrators.filtering")


def _refuse(name: str, why: str):
    def ctor(props):
        raise RuntimeError(
            f"{name}: {why} (variant '{mi.variant()}'). Use a JIT variant such as 'llvm_ad_rgb', "
            "'llvm_ad_spectral' or 'cuda_ad_rgb' (mi.set_variant(...))."
        )

    return ctor


def register() -> None:
    """Register every integrator of the package for the current Mitsuba variant (no-op without one)."""
    variant = mi.variant()
    if variant is None:
        return
    for base in _BASES:
        if not variant.startswith("scalar") and base in sys.modules:
            importlib.reload(sys.modules[base])  # the classes must derive from this variant's classes
    for name, module in INTEGRATORS.items():
        if variant.startswith("scalar"):
            mi.register_integrator(name, _refuse(name, "segmitsuba's integrators are wavefront (Dr.Jit JIT) "
                                                       "integrators and cannot run in a scalar variant"))
            continue
        if "polarized" in variant:
            mi.register_integrator(name, _refuse(name, "polarized transport is not supported"))
            continue
        full = f"segmitsuba.integrators.{module}"
        if full in sys.modules:
            importlib.reload(sys.modules[full])
        else:
            importlib.import_module(full)
