"""glibc's allocator told to keep what a process frees, for the next batch or fit of the same size.

By default glibc hands a freed buffer above its adaptive threshold (128 KB, rising to at most
32 MB) back to the kernel, and the next buffer of that size faults every page in again, zeroed by
the kernel. A trainer on a CPU allocates the same buffers every batch: at 64 px and a batch of 256
the heat maps (x3) alone are 32 MB, 128 MB at 128 px. Kept, the input path on one core gains 63%
at 128 px and 2.1x at 256 px with reframing (at 64 px within noise), 2.5-3.5x without reframing
(BENCHMARKS.md, "The input path"); a Dask worker's fits, 1.7x. Elsewhere than glibc there is
nothing to set.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (malloc.h)
# The most M_MMAP_THRESHOLD glibc before 2.35 takes (HEAP_MAX_SIZE / 2 on 64 bits); later ones take more
OLD_GLIBC_MOST = 32 << 20


def keep_freed_memory(mmap_threshold: int, trim_threshold: int) -> bool:
    """Buffers up to `mmap_threshold` bytes (or the most this glibc takes, if less) come from the
    heap rather than their own mapping, and up to `trim_threshold` bytes freed at the heap's top
    stay mapped; glibc's adaptive thresholds are then off. The trim is only set once the mmap
    threshold is: alone it would freeze that at 128 KB and map every larger buffer afresh.
    True where glibc took both; False elsewhere (no glibc), nothing changed."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if not (mallopt(M_MMAP_THRESHOLD, mmap_threshold) or mallopt(M_MMAP_THRESHOLD, min(mmap_threshold, OLD_GLIBC_MOST))):
        return False
    return bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))
