"""Process-wide settings for command-line runs and benchmarks (never set by the libraries).

Batched solvers allocate many short-lived tensors of a few megabytes. glibc serves blocks
above 128 KiB with fresh ``mmap`` pages and unmaps them on free, so every such temporary is
page-faulted in again, one 4 KiB page at a time -- on this project's machines that costs
more than the arithmetic of an elementwise operation on it. Raising glibc's thresholds keeps
freed blocks for reuse, which speeds batched pose solving up and slows nothing else down
(docs/decisions/004-tuning-evidence.md). The process then keeps up to ``trim`` bytes of
freed memory mapped.
"""

from __future__ import annotations

import ctypes

__all__ = ["release_freed_memory", "retain_freed_memory"]

# mallopt parameters of glibc's <malloc.h>
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3


def retain_freed_memory(
    mmap_threshold: int = 32 << 20, trim: int = 256 << 20, top_pad: int = 64 << 20
) -> bool:
    """Ask glibc to serve blocks up to ``mmap_threshold`` bytes from the heap and to keep up
    to ``trim`` bytes of freed heap (growing it ``top_pad`` bytes at a time). Returns whether
    it took effect (``False`` without glibc, e.g. on macOS or musl: then nothing changes)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(
        mallopt(param, value) == 1
        for param, value in (
            (_M_MMAP_THRESHOLD, mmap_threshold),
            (_M_TRIM_THRESHOLD, trim),
            (_M_TOP_PAD, top_pad),
        )
    )


def release_freed_memory() -> bool:
    """Hand the memory this process has freed back to the system now (glibc's
    ``malloc_trim``): freed small blocks stay in glibc's heap, where they would sit under a
    later peak (e.g. a long synthetic video's intermediates under its registration). No
    result changes. Returns whether it ran (``False`` without glibc)."""
    try:
        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    trim(0)
    return True
