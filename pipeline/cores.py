"""The cores a scan may use, and what the process placement decides from them.

:func:`cores_available` is the one count every decision takes (OpenCV's threads,
:mod:`sffscan.pipeline.opencv_threads`; the band workers' ``auto``; one thread a worker
process, :func:`one_thread_per_process`): the affinity mask where the system has one (a
scan pinned with ``taskset`` or a container's CPU set), else every core.
"""

from __future__ import annotations

import os

__all__ = ["auto_band_workers", "cores_available", "one_thread_per_process"]


def cores_available() -> int:
    """The cores this process may run on (its affinity mask), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def auto_band_workers(cores: int) -> int:
    """``processing.workers = "auto"`` on ``cores`` cores: the cores less 2 (the
    registration and the main process), at least 1, at most 8."""
    return max(1, min(8, cores - 2))


def one_thread_per_process(processes: int) -> bool:
    """Whether each worker process of a placement of ``processes`` processes runs its stages
    in one thread (:class:`~sffscan.pipeline.runtime.Pipeline`'s ``one_thread``): where the
    cores available are no more than the processes, so that a process's stages would only
    take turns on its core.

    Measured on 2 cores with 3 processes (docs/performance-log.md, 2026-12-03): 112.4 ->
    121.3 frames/s from memory, 14.84 -> 13.58 ms of CPU a frame. With more cores than
    processes each stage keeps its thread, and the stages overlap.
    """
    return cores_available() <= processes
