"""Keep the server's resident memory flat: cap glibc's malloc arenas (Linux/glibc only; elsewhere a no-op).

Each request decodes six ~4 MB images on worker threads; glibc gives every thread its own malloc arena (up to
8 × cores) and keeps freed memory of each arena mapped, so the resident size of a busy server climbs by hundreds of
MiB before it levels off. Two arenas keep it flat at no measurable cost in throughput (docs/results.md#serving has the
figures). ``MALLOC_ARENA_MAX`` in the environment, when set, wins: glibc read it at start-up and it is left alone.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os

M_ARENA_MAX = -8  # from glibc's malloc.h
DEFAULT_ARENAS = 2
_done = False


def cap_malloc_arenas(arenas: int = DEFAULT_ARENAS) -> bool:
    """Call ``mallopt(M_ARENA_MAX, arenas)`` once, early (before worker threads start). True when applied."""
    global _done
    if _done or "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    _done = bool(mallopt(ctypes.c_int(M_ARENA_MAX), ctypes.c_int(arenas)))
    return _done
