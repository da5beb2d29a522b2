"""Keep frame-sized buffers in the heap instead of handing them back to the kernel after every frame.

Measured in the server process (glibc, after JAX has initialised): each 512x512 frame allocates and frees
0.75-3 MB buffers (the 2x drawing patch, the frame copy, the numpy view, the JPEG input), and glibc returned each
one to the kernel, so the next frame page-faulted it back in: about 600 minor faults and 1.4 ms of system time
per frame, which tripled the draw time (0.8 ms -> 2.3-3.5 ms). Fixed thresholds above the frame size keep those
buffers in the heap. malloc_trim still returns memory on demand (the session-memory test calls it).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1  # mallopt parameter numbers from glibc's malloc.h
_M_MMAP_THRESHOLD = -3
# The largest frame buffer is the 2x drawing patch of the largest canvas (frames.MAX_PIXELS = 1280x800):
# 2560x1600x3 ≈ 12 MB, so it stays below the mmap threshold.
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 64 << 20


def keep_frame_buffers_resident() -> bool:
    """Set glibc's mmap and trim thresholds (once per process); False where the C library is not glibc."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        mallopt = None
    if mallopt is None:
        log.debug("no glibc mallopt here; frame buffers use the C library's defaults")
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    return ok
