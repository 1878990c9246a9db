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
``bench/bench_bands.py`` measures it. The focus volume's bands can also run as named tasks
(:class:`BandTasks`, :mod:`sffscan.stages.volume_tasks`) on arrays of their own, each band
measuring the focus of the rows it accumulates: in processes, which share no GIL
(:mod:`sffscan.pipeline.band_processes`), or in threads (:class:`BandTaskThreads`, a
scan's band threads with the OpenCV backend), which pay no frame-sized focus measure
joined from the bands and split again (bench/results/band_task_threads.md).
"""

from __future__ import annotations

import collections
import contextlib
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

__all__ = ["BAND_CPU_KEY", "BandTaskThreads", "BandTasks", "BandWorkers", "row_bands"]

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


class BandTaskThreads:
    """:class:`BandTasks` in threads of this process: the layout's arrays in this process's
    memory, one thread a band after the first, the caller's thread the first.

    The same tasks (:mod:`sffscan.stages.volume_tasks`) on the same arrays as band
    processes, so the blocks are bit-identical to theirs and to one band; each band
    measures the focus of the rows it accumulates (no frame-sized focus measure gathered
    from the bands) and a frame is one task a band. What the bands' Python code holds of
    the GIL is shared, as for :class:`BandWorkers`.

    Parameters
    ----------
    k : int
        Bands, >= 1 (``k - 1`` threads).
    layout : dict
        Array name -> (shape, dtype string)
        (:meth:`sffscan.stages.shared_volume.SharedFocusVolume.shared_layout`).
    timeout_s : float, keyword-only
        The longest a wait for a band's task may take; past it the wait raises
        ``TimeoutError`` naming the task and rows.
    name : str, keyword-only
        The threads' name prefix.

    Notes
    -----
    Each band thread runs its tasks in the order they were submitted. A task's
    ``params`` are read when the band runs it: the caller must not change them after
    :meth:`submit_task`.
    """

    def __init__(self, k: int, layout: dict[str, tuple[tuple[int, ...], str]], *,
                 timeout_s: float = 120.0, name: str = "band") -> None:
        if k < 1:
            raise ValueError(f"k (band workers) must be >= 1, got {k}")
        self.k = k
        self.timeout_s = timeout_s
        self._arrays = {n: np.zeros(shape, np.dtype(dtype)) for n, (shape, dtype)
                        in layout.items()}
        self._pools = [ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{name}-{i}")
                       for i in range(1, k)]
        self._pending: list[collections.deque[tuple[int, Future[None], str]]] = [
            collections.deque() for _ in self._pools]
        self._ticket = 0
        self._closed = False

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays, by name."""
        return self._arrays

    def run_task(self, task: str, params: dict[str, Any],
                 bands: list[tuple[int, int]]) -> None:
        """:meth:`BandTasks.run_task`."""
        self.wait_tasks(self.submit_task(task, params, bands))

    def submit_task(self, task: str, params: dict[str, Any],
                    bands: list[tuple[int, int]]) -> int:
        """:meth:`BandTasks.submit_task`."""
        # imported at use: the tasks' modules (the depth estimators) are not this one's
        from sffscan.stages.volume_tasks import run_task

        if len(bands) > self.k:
            raise ValueError(f"{len(bands)} bands for {self.k} band workers")
        if self._closed:
            raise RuntimeError("band task threads used after they were closed")
        self._ticket += 1
        for (a, b), pool, pending in zip(bands[1:], self._pools, self._pending, strict=False):
            f = pool.submit(run_task, self._arrays, task, params, (a, b))
            pending.append((self._ticket, f, f"{task}, rows {a}..{b}"))
        if bands:
            try:
                run_task(self._arrays, task, params, bands[0])
            except BaseException:  # the other bands write into the same arrays: wait
                with contextlib.suppress(Exception):
                    self.wait_tasks(self._ticket)
                raise
        return self._ticket

    def wait_tasks(self, ticket: int | None = None) -> None:
        """:meth:`BandTasks.wait_tasks`: the first error a band raised on the way is raised
        (the others' tasks still waited for)."""
        upto = self._ticket if ticket is None else ticket
        failure: BaseException | None = None
        for pending in self._pending:
            while pending and pending[0][0] <= upto:
                _, f, what = pending.popleft()
                try:
                    f.result(timeout=self.timeout_s)
                except TimeoutError as err:
                    if failure is None:
                        failure = TimeoutError(
                            f"band thread ({what}) took more than {self.timeout_s:g} s")
                        failure.__cause__ = err
                except Exception as err:
                    failure = failure or err
        if failure is not None:
            raise failure

    def helpers_cpu_s(self) -> float:
        """0: the threads' CPU is this process's own."""
        return 0.0

    def close(self) -> None:
        """Join the threads (idempotent; tasks not started are dropped)."""
        self._closed = True
        for pool in self._pools:
            pool.shutdown(wait=True, cancel_futures=True)
        self._pools = []

    def __enter__(self) -> BandTaskThreads:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
