"""glibc's heap settings for a process that runs the scan's stages (:func:`keep_freed_memory`)."""

from __future__ import annotations

import ctypes
import sys

__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "keep_freed_memory"]

#: glibc ``mallopt`` parameters (malloc.h) and the values :func:`keep_freed_memory` sets
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 2**20  # glibc's largest on 64-bit
TRIM_THRESHOLD_BYTES = 256 * 2**20


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed memory in the process instead of giving it back at once.

    By default an array over 128 KiB to a few MiB (a frame's reduced copy, a crop's
    spectrum, a column range of the focus measure) is mapped fresh from the kernel and
    unmapped when freed, and the stage threads' heaps are trimmed as soon as their top is
    free: every frame then pays page faults and the zeroing of new pages again. Measured
    with perf in the registration and focus workers (1280 x 1024 default scan): 0.6-0.9 ms
    of kernel time per frame each; with these settings the registration stage's CPU went
    from 4.7-5.3 to 3.5-4.0 ms per frame (3 interleaved runs each). Arrays up to
    :data:`MMAP_THRESHOLD_BYTES` come from the heap, and a heap gives memory back only
    when :data:`TRIM_THRESHOLD_BYTES` are free at its top: a worker keeps its peak use
    until it exits (the arrays of one frame, a few tens of MB), nothing grows with the
    scan. Worker processes call it, and the ``sffscan`` command in its own process, not the
    library's functions nor ``main(argv)`` called from another program (a caller's process
    is the caller's). Returns whether both settings took (False off glibc).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
                and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
