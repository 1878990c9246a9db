"""How many threads OpenCV's own pool runs in a scan's processes.

OpenCV parallelises a call over every core by default, in every process, beside the
stages that already run in parallel (one thread each in the thread placement, one process
each in the process placement). Where the machine has no more cores than those parallel
parts, its pool only competes with them, and its idle threads spin and yield between
calls. Measured (2026-12-03, the 2-core AMD EPYC VM of docs/performance-log.md,
``bench_parallel.py --quick --frames 600 --cores 2 --method default``, 4 rounds alternating
with ``OPENCV_FOR_THREADS_NUM=1``): processes from memory 90.6 -> 98.7 frames/s (median; 4
of 4 pairs faster), 18.9 -> 16.6 ms of CPU a frame (every pair less); threads 4 of 4 pairs
less CPU; replay 3 of 3 pairs faster; with the recorder on no gain (2 of 6 pairs faster, 3 slower:
its process waits on its writes, and OpenCV's threads elsewhere used that core). On
machines with more cores than parallel parts OpenCV keeps its default (not measured
there). A user's ``OPENCV_FOR_THREADS_NUM`` is always left to rule.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator

from sffscan.pipeline.cores import cores_available

__all__ = ["opencv_thread_limit", "opencv_threads"]


def opencv_threads(parts: int) -> int | None:
    """OpenCV threads for each of ``parts`` stages or processes that compute at once: 1
    where the cores available (the affinity mask) are no more than ``parts``, else None
    (OpenCV's default); None too where ``OPENCV_FOR_THREADS_NUM`` is set."""
    if "OPENCV_FOR_THREADS_NUM" in os.environ:
        return None
    return 1 if cores_available() <= parts else None


class _Holders:
    """Who holds a limit now, and OpenCV's setting before the first of them: process-wide
    state, as ``cv2.setNumThreads`` is (runs overlapping in one process, e.g. several
    threads of a Dask worker, must not leave the limit behind when they end out of
    order)."""

    lock = threading.Lock()
    count = 0
    before = 0


@contextlib.contextmanager
def opencv_thread_limit(threads: int | None) -> Iterator[None]:
    """OpenCV's pool at ``threads`` while the block runs, then as it was before the first
    of the overlapping blocks began, once the last has ended (None: untouched).

    ``cv2.setNumThreads`` is process-wide: another thread's OpenCV calls in this process
    run with the same limit meanwhile."""
    if threads is None:
        yield
        return
    import cv2

    with _Holders.lock:
        if _Holders.count == 0:
            _Holders.before = cv2.getNumThreads()
        _Holders.count += 1
        cv2.setNumThreads(threads)
    try:
        yield
    finally:
        with _Holders.lock:
            _Holders.count -= 1
            if _Holders.count == 0:
                cv2.setNumThreads(_Holders.before)
