"""Make Dr.Jit load a working libLLVM (>= 16) before it is imported.

Debian's default libLLVM 15 aborts Dr.Jit on AVX-512 CPUs (``LLVM ERROR: Cannot select ... fmaximum``).
``DRJIT_LIBLLVM_PATH`` is only read when ``drjit`` is imported, so this module must run first and must not
import ``drjit`` itself.
"""

from __future__ import annotations

import glob
import os
import re
import sys

MIN_VERSION = 16

_SEARCH = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)


def _version(path: str) -> int:
    """Major version encoded in a libLLVM file name (``libLLVM-19.so``, ``libLLVM.so.19.1``), or 0."""
    name = os.path.basename(path)
    m = re.search(r"libLLVM[-.](?:so\.)?(\d+)", name) or re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else 0


def find_libllvm() -> str | None:
    """The newest libLLVM >= 16 on this machine, or None."""
    found = [p for pat in _SEARCH for p in glob.glob(pat) if _version(p) >= MIN_VERSION]
    found.sort(key=lambda p: (_version(p), -len(p)))
    return found[-1] if found else None


FIX = (
    "Dr.Jit needs libLLVM >= 16 here (Debian's libLLVM 15 aborts on AVX-512 CPUs). On Debian/Ubuntu run "
    "'sudo apt-get install libllvm19' (or 'make demo', which does it), and either import segmitsuba before "
    "drjit/mitsuba or set DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 before starting Python."
)


def configure() -> None:
    """Point Dr.Jit at a good libLLVM, or check the one already loaded."""
    if "drjit" not in sys.modules:
        current = os.environ.get("DRJIT_LIBLLVM_PATH")
        if current and os.path.exists(current) and (_version(current) == 0 or _version(current) >= MIN_VERSION):
            return  # the user's own choice (a version we cannot read from the name is trusted)
        lib = find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
        return
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        return
    major = dr.detail.llvm_version()[0]
    if 0 < major < MIN_VERSION:
        raise ImportError(
            f"segmitsuba: Dr.Jit was already imported with libLLVM {major}, which crashes on this CPU. " + FIX
        )
