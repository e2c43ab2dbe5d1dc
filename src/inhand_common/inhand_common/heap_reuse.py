"""Keep freed memory for the next frame instead of returning it to the kernel.

glibc's malloc serves a large request (a 640x480 image's points, a map's cloud: several MB)
with a fresh mmap and gives it back with munmap when freed; the next frame's request of the
same size starts again from untouched pages, and the kernel zeroes each on its first write.
A node handles a frame-sized buffer many times a second, so it paid that every time:
measured on the stereo node's segmentation of one 640x480 pair, 1,612 page faults and
11-13 ms a call; with freed memory kept for reuse, none and 7 ms. Every node calls
:func:`reuse_freed_memory` at start (node_runner.py), as a real-time system pre-faults its
heap. The process keeps its peak heap (what it needed once it will need again).
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ['MMAP_THRESHOLD', 'TRIM_THRESHOLD', 'reuse_freed_memory']

# mallopt's parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024     # requests below this come from the heap (glibc's cap)
TRIM_THRESHOLD = 256 * 1024 * 1024    # free memory at the heap's top kept up to this


def reuse_freed_memory() -> bool:
    """Set glibc's malloc to serve requests up to 32 MiB from the heap and keep up to
    256 MiB of freed memory there. False where the C library is not glibc (nothing
    changes)."""
    name = ctypes.util.find_library('c')
    try:
        libc = ctypes.CDLL(name or 'libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
