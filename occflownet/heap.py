"""Keep freed tensor memory in the process for reuse (glibc's malloc), instead of handing it back to the kernel.

torch's CPU allocator takes every tensor from ``malloc``. glibc serves a request above its mmap threshold (128 KiB
at first, raised up to 32 MiB by what the process frees) with a fresh ``mmap`` and returns it with ``munmap``; the
heap's top is also returned once more than the trim threshold lies free there. Each training step allocates and
frees the same tensors of tens of MiB (``[640000, 16]`` float32 is 41 MiB: the decoder's rows of one sample), so
every step faulted their pages in again and the kernel zeroed them: an element-wise pass over such a tensor took
3-4x as long as over memory already mapped (docs/results.md, "Training speed").

:func:`reuse_freed_memory` raises both thresholds for this process, so those tensors come from the heap and
their pages stay mapped between steps. The cost: memory freed at the peak stays with the process until it exits
(the resident size stays at the peak instead of falling between steps). Without glibc (macOS, musl) it does
nothing; a user who set ``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_`` or ``GLIBC_TUNABLES`` keeps those.
"""
from __future__ import annotations

import ctypes
import os
import platform

M_TRIM_THRESHOLD = -1                 # mallopt parameters (glibc's malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 1 << 30              # requests up to 1 GiB come from the heap
TRIM_THRESHOLD = (1 << 31) - 1        # the largest int: the heap is not trimmed while the process runs
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")


def reuse_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (see the module's docstring); returns whether they
    were set (False without glibc, or where the user's environment already sets malloc's tunables)."""
    if platform.libc_ver()[0] != "glibc" or any(name in os.environ for name in USER_SETTINGS):
        return False
    mallopt = ctypes.CDLL(None).mallopt            # glibc is loaded in every glibc process: no library search
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
