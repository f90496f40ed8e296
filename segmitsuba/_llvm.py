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
import warnings

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


def _libllvms() -> list[str]:
    return [p for pat in _SEARCH for p in glob.glob(pat)]


def find_libllvm() -> str | None:
    """The newest libLLVM >= 16 on this machine, or None."""
    found = [p for p in _libllvms() if _version(p) >= MIN_VERSION]
    found.sort(key=lambda p: (_version(p), -len(p)))
    return found[-1] if found else None


def _has_avx512() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx512f" in line for line in f)
    except OSError:
        return False


FIX = (
    "Dr.Jit needs libLLVM >= 16 here (Debian's libLLVM 15 aborts on AVX-512 CPUs). On Debian/Ubuntu run "
    "'sudo apt-get install libllvm19' (or 'make demo', which does it), and either import segmitsuba before "
    "drjit/mitsuba or set DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 before starting Python."
)


def missing_llvm_warning(versions: list[int], avx512: bool) -> str | None:
    """What to say where no libLLVM >= 16 was found: Dr.Jit will load one of ``versions`` (the older ones found)
    and, on an AVX-512 CPU, abort at its first kernel; None where nothing is known to fail."""
    if not avx512 or not versions or max(versions) >= MIN_VERSION:
        return None
    return (f"segmitsuba: the only libLLVM found is version {max(versions)}, which aborts Dr.Jit on this CPU "
            f"(LLVM ERROR: Cannot select ... fmaximum). " + FIX)


def configure() -> None:
    """Point Dr.Jit at a good libLLVM, or check the one already loaded."""
    if "drjit" not in sys.modules:
        current = os.environ.get("DRJIT_LIBLLVM_PATH")
        if current and os.path.exists(current) and (_version(current) == 0 or _version(current) >= MIN_VERSION):
            return  # the user's own choice (a version we cannot read from the name is trusted)
        lib = find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
        else:
            message = missing_llvm_warning(sorted({_version(p) for p in _libllvms()} - {0}), _has_avx512())
            if message:
                warnings.warn(message, RuntimeWarning, stacklevel=3)
        return
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        return
    major = dr.detail.llvm_version()[0]
    if 0 < major < MIN_VERSION:
        raise ImportError(
            f"segmitsuba: Dr.Jit was already imported with libLLVM {major}, which crashes on this CPU. " + FIX
        )
