"""Band workers: a frame's rows split among K threads of one stage.

The focus measure, the accumulation and the reduction to depth are local in the rows of a
frame: a pixel's result depends on the rows within a fixed reach of it (the focus window,
the median and spread filters). :func:`row_bands` cuts the rows into K bands,
:class:`BandWorkers` runs one function per band, each band in its own thread, the caller's
thread taking the first. Each band reads its rows widened by the reach and keeps its own
rows, so the result is bit-identical for every K (tested in
``tests/stages/test_bands.py``).

Threads: the work inside a band is OpenCV and numpy on arrays of a few hundred rows,
which release the GIL, and the bands share the frame and the focus volume's state without
copies. What still holds the GIL (the calls' Python overhead) limits the gain;
``bench/bench_bands.py`` measures it. The focus volume's bands can also run in processes
(:class:`BandTasks`, :mod:`sffscan.pipeline.band_processes`), which share no GIL.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

__all__ = ["BAND_CPU_KEY", "BandTasks", "BandWorkers", "row_bands"]

BAND_CPU_KEY = "band_processes_cpu_s"
"""A stage's statistic (:meth:`~sffscan.stages.protocol.Stage.extra_stats`): CPU seconds
its band processes, other than the stage's own, used while streaming; the process that
runs the stage counts it with its own CPU."""

T = TypeVar("T")
A = TypeVar("A")


def row_bands(start: int, stop: int, k: int) -> list[tuple[int, int]]:
    """Rows [start, stop) cut into at most ``k`` contiguous bands of near-equal height.

    Parameters
    ----------
    start, stop : int
        The rows, ``start <= stop``.
    k : int
        Number of bands, >= 1 (fewer when there are fewer rows).

    Returns
    -------
    list of (int, int)
        ``(r0, r1)`` per band, in order, covering [start, stop) without overlap; empty
        when there are no rows.
    """
    if k < 1:
        raise ValueError(f"k (band workers) must be >= 1, got {k}")
    n = stop - start
    if n <= 0:
        return []
    k = min(k, n)
    edges = [start + (n * i) // k for i in range(k + 1)]
    return list(zip(edges[:-1], edges[1:], strict=True))


@runtime_checkable
class BandTasks(Protocol):
    """Band workers in other processes (:class:`sffscan.pipeline.band_processes.BandProcesses`):
    they share ``arrays`` (named, in shared memory) with the caller and run named tasks
    (:mod:`sffscan.stages.volume_tasks`) on bands of their rows."""

    k: int

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        """The shared arrays, by name."""

    def run_task(self, task: str, params: dict[str, Any],
                 bands: list[tuple[int, int]]) -> None:
        """Run ``task`` with ``params`` on every band at once; return when all are done,
        and every task submitted before it (raise, naming the band, where one failed)."""

    def submit_task(self, task: str, params: dict[str, Any],
                    bands: list[tuple[int, int]]) -> int:
        """Start ``task`` on every band, the caller's own band done before it returns, the
        others run in order after the tasks submitted before; returns a ticket for
        :meth:`wait_tasks` (what the task reads must not change, what it writes must not be
        read, until then)."""

    def wait_tasks(self, ticket: int | None = None) -> None:
        """Wait until the task of ``ticket`` (None: every task) is done on every band."""

    def helpers_cpu_s(self) -> float:
        """CPU seconds the other processes have used on the tasks."""

    def close(self) -> None:
        """Stop the processes (idempotent)."""


class BandWorkers:
    """Runs a function on each band of rows, the bands in parallel threads.

    Parameters
    ----------
    k : int
        Band workers, >= 1. With 1 every call runs in the caller's thread.
    timeout_s : float
        The longest a band may take; past it :meth:`run` raises ``TimeoutError`` naming
        the band (the pool is then unusable: the stage fails, as any stage error does).

    Notes
    -----
    The pool has ``k - 1`` threads, the caller runs the first band. A call waits for all
    its bands; at most ``k - 1`` tasks are queued at any time (one call at a time per
    pool). :meth:`close` joins the threads.
    """

    def __init__(self, k: int, *, timeout_s: float = 120.0, name: str = "band") -> None:
        if k < 1:
            raise ValueError(f"k (band workers) must be >= 1, got {k}")
        self.k = k
        self.timeout_s = timeout_s
        self._pool = (ThreadPoolExecutor(max_workers=k - 1, thread_name_prefix=name)
                      if k > 1 else None)

    def run(self, fn: Callable[[int, int], T], bands: list[tuple[int, int]]) -> list[T]:
        """``[fn(r0, r1) for (r0, r1) in bands]``, the bands after the first in the pool."""
        return self.map(lambda band: fn(*band), bands,
                        name=lambda band: f"band worker for rows {band[0]}..{band[1]}")

    def map(self, fn: Callable[[A], T], items: Sequence[A], *,
            name: Callable[[A], str] = lambda item: f"worker for {item!r}") -> list[T]:
        """``[fn(item) for item in items]``, the items after the first in the pool, the
        first in the caller's thread; returns once every item is done, in their order.
        ``name(item)`` names an item that takes longer than :attr:`timeout_s`."""
        if self._pool is None or len(items) < 2:
            return [fn(item) for item in items]
        futures = [self._pool.submit(fn, item) for item in items[1:]]
        try:
            first = fn(items[0])
        finally:
            # every item finishes (or times out) before the caller goes on: they write
            # into arrays the caller owns
            rest = []
            for item, f in zip(items[1:], futures, strict=True):
                try:
                    rest.append(f.result(timeout=self.timeout_s))
                except TimeoutError as err:
                    raise TimeoutError(f"{name(item)} took more than "
                                       f"{self.timeout_s:g} s") from err
        return [first, *rest]

    def close(self) -> None:
        """Join the pool's threads (idempotent)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> BandWorkers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
