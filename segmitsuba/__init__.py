"""segmitsuba: segment-based light transport for Mitsuba 3.

Importing the package registers its integrators (``segment_pt``, ``segment_lt``, ...) with Mitsuba for the
current variant and for every variant set later, so ``mi.load_dict({'type': 'segment_pt'})`` works like a
built-in plugin.
"""

from __future__ import annotations

from . import _llvm

_llvm.configure()  # must precede the first `import drjit`

import mitsuba as mi  # noqa: E402


class SparsePoolWarning(UserWarning):
    """Most kernel domains of a ``segment_bdf`` pool hold about two walk vertices: the estimate is biased
    upwards (docs/maths.md §8.1, item 4). Defined here, not with the integrators, whose modules are imported
    again for every variant: one class for every variant, importable before a variant is set."""


class KernelSizeWarning(UserWarning):
    """A filter's kernel is wider than the whole scene (a film of a few pixels, whose footprints size the
    derived kernel, or a ``kernel_size`` too large): its image is then biased far beyond a blur."""


from .registry import INTEGRATORS, register  # noqa: E402

__version__ = "0.1.0"
__all__ = ["INTEGRATORS", "KernelSizeWarning", "SparsePoolWarning", "register", "__version__"]

register()  # for the current variant, if one is set
mi.detail.add_variant_callback(lambda old, new: register())
