"""glibc allocator settings for CPU training and inference: keep freed tensor memory in the heap.

By default glibc serves every block over its mmap threshold (≤ 32 MB) with a fresh mmap and
returns it on free, so each forward pass page-faults its activations in again, which can be more
than half of a small mesh's inference time. No effect off glibc; set
HEARTCTL_MALLOC_TUNE=0 to leave the allocator alone."""
from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4
_done = False


def tune_allocator() -> bool:
    """Serve large blocks from the heap (no mmap), trim it only above 1 GiB free; once per process."""
    global _done
    if _done or os.environ.get("HEARTCTL_MALLOC_TUNE", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(M_MMAP_MAX, 0) == 1
        ok &= libc.mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1
        ok &= libc.mallopt(M_TOP_PAD, 64 << 20) == 1
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return False
    _done = True
    return bool(ok)
