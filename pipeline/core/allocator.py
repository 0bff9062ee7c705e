"""glibc's allocator set for a stream of video frames.

A decoded frame is megabytes (2.7 MB at 1280×720). With glibc's default, dynamic thresholds,
frames that a decode thread allocates and the consumer frees are handed back to the kernel when
the heap's free top passes the trim threshold, and faulted in again, page by page, for the next
frames: the detect stage took 19–24 k page faults per 150-frame 1280×720 clip, against 1.4–2.2 k
with the thresholds fixed (and the system time those faults cost). The peak memory of a ``run`` is the
same within a few MB (``benchmarks/memory.py`` measures it as the CLI runs).

The CLI sets this in its own process (:func:`tune`) and every child it starts inherits it through
the environment (:data:`ENV`); a value the user set wins. A program that calls stereotrack's
functions itself may call :func:`tune` first; importing stereotrack changes nothing. Elsewhere
(musl, macOS) nothing changes.
"""

from __future__ import annotations

import ctypes
import os

#: allocations above this are mmap'd, below from the heap (glibc's largest allowed value)
MMAP_THRESHOLD = 32 << 20
#: free memory at the heap's top kept before trimming (about twenty 1280×720 frames and more)
TRIM_THRESHOLD = 128 << 20
#: the same settings as environment variables, read by glibc at a process's start
ENV = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameter numbers (malloc.h)


def tune() -> bool:
    """Set both thresholds in this process with ``mallopt`` (glibc only; skipped where the user
    set either variable). True when set. Both together, or neither: either alone turns off
    glibc's dynamic thresholds and makes the stage up to 2× slower."""
    if any(k in os.environ for k in ENV):
        return False
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):
            return False
        libc = ctypes.CDLL(None)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(_M_TRIM_THRESHOLD,
                                                                                        TRIM_THRESHOLD))
    except (OSError, AttributeError, ValueError):
        return False


def trim() -> None:
    """Hand the heap's free memory back to the kernel now (glibc's ``malloc_trim``; elsewhere
    nothing). The thresholds above keep a frame stream's pages; the results a forked worker sends
    are unpickled in the pool's reader thread, whose heap they would keep for the rest of the run."""
    try:
        if os.confstr("CS_GNU_LIBC_VERSION"):
            ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError, ValueError):
        pass
