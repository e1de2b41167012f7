"""The host allocator's policy for the cpu backend: freed arrays stay with the process.

Every frame the cpu odometry makes arrays of a few megabytes and frees them: the valid points of
a 640x480 level (6.5 MB), the RGB-D correspondences (2.4 MB), the loops' work arrays on each
thread. glibc's malloc returns such blocks to the system (it maps a block above its
threshold, which it raises only as larger blocks are freed, and trims a heap whose free top
outgrows twice that), so the next frame's arrays start as fresh pages: on the 2-core VM about
1400 page faults a frame in the odometry, each 1.7 us (a fresh 6.5 MB array written costs
0.95 ms, a reused one 0.01 ms), until some larger block happened to raise the thresholds. Fixed
thresholds keep the blocks in the heap for the next frame. Other C libraries keep their own
policy (no mallopt there: nothing is changed).
"""

from __future__ import annotations

import ctypes

# mallopt's parameters (glibc's malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# Blocks below this come from the heap, so they are reused; glibc accepts at most 32 MiB here
# on 64-bit machines (a 1280x960 level's valid points are 26 MB).
MMAP_THRESHOLD = 32 << 20
# The free top a heap keeps before it returns memory to the system: a frame's arrays, twice.
TRIM_THRESHOLD = 64 << 20


def hold_freed_memory() -> bool:
    """Fix glibc's malloc thresholds (MMAP_THRESHOLD, TRIM_THRESHOLD) for this process, so that
    the arrays a frame frees serve the next frame without new page faults. True where the C
    library took them; False where it has no mallopt or refused (its policy stays)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
