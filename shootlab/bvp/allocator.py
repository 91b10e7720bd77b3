"""Memory allocator settings for the batched tensors of the shooting code (glibc, Linux).

The interval integrations and their forward sensitivities create and free tensors of tens to
hundreds of megabytes many times per Newton iteration (tangents of the right-hand side,
(m, n, n) blocks).  glibc's ``malloc`` serves blocks above its mmap threshold (128 KiB, growing
to at most 32 MiB) with fresh ``mmap`` pages and returns them to the kernel on ``free``, so every
such tensor costs page faults and zero-filling in the kernel: on the 20-element mixture
estimation (n = 44, m = 201) the kernel's time exceeds the computation's, and the solve takes
about twice as long as with the settings below.  PyTorch's CPU performance guide recommends a
caching allocator (jemalloc, tcmalloc) for the same reason; :func:`tune` gets the effect from glibc itself:

    M_MMAP_THRESHOLD  1 GiB     blocks up to 1 GiB come from the heap, reused after free
    M_TRIM_THRESHOLD  2 GiB − 1    freed heap memory is kept for the next tensors, not trimmed
    M_TOP_PAD         256 MiB   the heap grows in large steps

The price: the process keeps the memory of its largest iteration until it exits.  Applied on
import of :mod:`shootlab` unless ``SHOOTLAB_MALLOC=default``; a no-op where the C library is
not glibc (macOS, Windows, musl).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["tune", "SETTINGS"]

#: mallopt parameter number → value (glibc's <malloc.h>)
SETTINGS = {-3: 1 << 30,        # M_MMAP_THRESHOLD
            -1: 2 ** 31 - 1,    # M_TRIM_THRESHOLD (mallopt takes an int)
            -2: 1 << 28}        # M_TOP_PAD

_applied: bool | None = None


def tune() -> bool:
    """Apply :data:`SETTINGS` with glibc's ``mallopt`` once; True if they are in effect."""
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get("SHOOTLAB_MALLOC", "").lower() == "default" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _applied = all(mallopt(param, value) == 1 for param, value in SETTINGS.items())
    return _applied
