"""Band processes: the focus volume's rows split among K processes that share its state.

Band threads (:class:`sffscan.stages.bands.BandWorkers`) share one interpreter: their
Python code takes turns on the GIL, so K threads cost more CPU per frame than one
(bench/results/bands.md: 1.23x for 2, 1.41x for 4 on 2 cores). :class:`BandProcesses`
runs the same work in K - 1 helper processes and the caller's own, each on its band of
rows. The focus volume's per-pixel state, the frame being added and a block's scratch are
named arrays in one shared-memory segment (laid out by
:meth:`sffscan.stages.shared_volume.SharedFocusVolume.shared_layout`); a task is a name and
JSON parameters (:mod:`sffscan.stages.volume_tasks`), sent down a pipe to each helper,
its answer an acknowledgement (with the helper's CPU time) or the error it raised; a
task may be submitted without waiting for the answers (:meth:`BandProcesses.submit_task`,
each helper runs its tasks in the order they came) and waited for later. Each
band reads its rows widened by the filters' reach, as with threads, so the blocks are
bit-identical for any K (``tests/pipeline/test_band_processes.py``).

Lifetime, as for the pipeline's other helpers (:mod:`sffscan.pipeline.spawn`): spawned,
they die with their parent (``PR_SET_PDEATHSIG``, and a pipe at end of file); the segment
is unlinked as soon as they have mapped it, so no name is left in ``/dev/shm`` whatever
happens; :meth:`BandProcesses.close` stops and joins them (terminated past
:data:`~sffscan.pipeline.spawn.JOIN_TIMEOUT_S`). Every wait has a timeout: a helper that
died or took longer than ``timeout_s`` fails the call with its name and rows.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import secrets
import threading
import time
import traceback
import weakref
from multiprocessing import shared_memory
from typing import Any

import numpy as np
from sffscan.pipeline.heap import keep_freed_memory
from sffscan.pipeline.shm_ring import aligned, map_now
from sffscan.pipeline.spawn import (
    START_TIMEOUT_S,
    WAIT_S,
    helper_start,
    join_or_kill,
    spawn_context,
)
from sffscan.stages.volume_tasks import Layout, run_task

__all__ = ["BandProcessFailed", "BandProcesses", "LazyBandProcesses", "map_arrays",
           "segment_bytes"]

SHM_DIR = "/dev/shm"  # where Linux keeps POSIX shared memory


class BandProcessFailed(RuntimeError):
    """A band process raised, died or did not answer in time."""


class _Silent(BandProcessFailed):
    """A band process that died or did not answer: nothing more is waited for from it (one
    that raised goes on answering its tasks in turn)."""


def _offsets(layout: Layout) -> tuple[dict[str, int], int]:
    off, pos = {}, 0
    for name, (shape, dtype) in layout.items():
        off[name] = pos
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        pos += aligned(n)  # each array starts on a cache line
    return off, pos


def segment_bytes(layout: Layout) -> int:
    """Bytes of the segment that holds ``layout``'s arrays."""
    return max(_offsets(layout)[1], 1)


def map_arrays(buf: Any, layout: Layout) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``layout``'s arrays over the buffer ``buf`` (a segment's ``memoryview``), and the
    byte array they are all views of (their ``base``: alive while any of them is)."""
    off, size = _offsets(layout)
    base = np.ndarray((size,), np.uint8, buffer=buf)
    return base, {name: base[off[name]:off[name] + int(np.prod(shape)) * np.dtype(dtype)
                             .itemsize].view(np.dtype(dtype)).reshape(shape)
                  for name, (shape, dtype) in layout.items()}


def _check_room(size: int, folder: str = SHM_DIR) -> None:
    """Refuse a segment that the shared-memory file system cannot hold (its pages are
    touched at once: past the room a write would kill the process with SIGBUS)."""
    try:
        st = os.statvfs(folder)
    except OSError:  # no such folder (not Linux): the platform's own error, if any
        return
    free = st.f_bavail * st.f_frsize
    if size > free:
        raise BandProcessFailed(
            f"band processes need {size / 2**20:.0f} MiB of shared memory, {folder} has "
            f"{free / 2**20:.0f} MiB free (a container's /dev/shm: docker run --shm-size); "
            f"or set processing.bands = 'threads'")


def _close_segment(shm: shared_memory.SharedMemory) -> None:
    """Unmap ``shm`` (once no array of it is left; at exit, whatever is left)."""
    with contextlib.suppress(BufferError):
        shm.close()


def _helper_main(conn: Any, segment: str, layout: dict[str, Any], parent: int,
                 opencv_threads: int | None) -> None:
    """A band process: map the segment, then run the tasks that come down ``conn``."""
    helper_start(parent)
    keep_freed_memory()  # a band's arrays of each frame: no fresh pages every frame
    import cv2
    from threadpoolctl import threadpool_limits

    if opencv_threads is not None:
        cv2.setNumThreads(opencv_threads)
    shm = shared_memory.SharedMemory(name=segment)
    map_now(shm, write=True)  # it writes its rows
    lay: Layout = {k: (tuple(v[0]), v[1]) for k, v in layout.items()}
    base, arrays = map_arrays(shm.buf, lay)
    with threadpool_limits(limits=1, user_api="blas"):
        conn.send_bytes(json.dumps({"cpu_s": time.process_time()}).encode())  # ready
        while True:
            try:
                if not conn.poll(WAIT_S):
                    if os.getppid() != parent:
                        os._exit(1)
                    continue
                msg = json.loads(conn.recv_bytes())
            except (EOFError, OSError):  # the parent is gone
                os._exit(1)
            if msg["task"] == "stop":
                break
            try:
                run_task(arrays, msg["task"], msg["params"], tuple(msg["rows"]))
                reply: dict[str, Any] = {"cpu_s": time.process_time()}
            except Exception as err:  # reported to the caller, which fails the stage
                reply = {"error": f"{type(err).__name__}: {err}",
                         "traceback": traceback.format_exc()}
            conn.send_bytes(json.dumps(reply).encode())
    del arrays, base
    _close_segment(shm)
    conn.send_bytes(json.dumps({"cpu_s": time.process_time()}).encode())


class BandProcesses:
    """K band workers: the caller's process and K - 1 helpers sharing ``layout``'s arrays.

    Parameters
    ----------
    k : int
        Band workers, >= 1 (1: no helper, the tasks run in the caller on the shared arrays).
    layout : dict
        The arrays, name -> (shape, dtype string)
        (:meth:`sffscan.stages.shared_volume.SharedFocusVolume.shared_layout`); zero-filled.
    timeout_s : float, keyword-only
        The longest a band's task may take before the call fails.
    name : str, keyword-only
        The helpers' process names (``sffscan-<name>-<i>``) and the segment's label.
    opencv_threads : int or None, keyword-only
        OpenCV threads in each helper (None: OpenCV's default).

    Attributes
    ----------
    arrays : dict of str to ndarray
        The shared arrays (this process's mapping).
    """

    def __init__(self, k: int, layout: Layout, *, timeout_s: float = 120.0,
                 name: str = "band", opencv_threads: int | None = 1) -> None:
        if k < 1:
            raise ValueError(f"k (band workers) must be >= 1, got {k}")
        self.k = k
        self.timeout_s = timeout_s
        self.name = name
        self._procs: list[Any] = []
        self._conns: list[Any] = []
        self._lock = threading.Lock()  # one task at a time (the stages' threads share it)
        self._cpu = [0.0] * (k - 1)
        self._ticket = 0  # tasks submitted
        # each helper's tasks not yet answered: (ticket, what), in the order sent
        self._pending: list[collections.deque[tuple[int, str]]] = [
            collections.deque() for _ in range(k - 1)]
        self._cpu0 = [0.0] * (k - 1)
        self.arrays: dict[str, np.ndarray] = {}
        _check_room(segment_bytes(layout))
        self._shm = shared_memory.SharedMemory(
            name=f"sffscan-{os.getpid()}-{name}-{secrets.token_hex(4)}", create=True,
            size=segment_bytes(layout))
        self._unlinked = False
        try:
            map_now(self._shm, write=True)
            base, self.arrays = map_arrays(self._shm.buf, layout)
            # unmapped when the last array is gone, the volume's views included
            weakref.finalize(base, _close_segment, self._shm)
            del base
            self._start(layout, opencv_threads)
        except BaseException:
            self.close()
            raise
        self._unlink()  # every helper has mapped it

    def _start(self, layout: Layout, opencv_threads: int | None) -> None:
        ctx = spawn_context()
        lay = {k: [list(v[0]), v[1]] for k, v in layout.items()}
        for i in range(1, self.k):
            mine, theirs = ctx.Pipe(duplex=True)
            p = ctx.Process(target=_helper_main, name=f"sffscan-{self.name}-{i}",
                            args=(theirs, self._shm.name, lay, os.getpid(), opencv_threads),
                            daemon=True)
            p.start()
            theirs.close()
            self._procs.append(p)
            self._conns.append(mine)
        for i in range(1, self.k):
            self._receive(i, START_TIMEOUT_S, "start")
        self._cpu0 = list(self._cpu)  # their start-up (imports) is not the stages' work

    def _receive(self, i: int, timeout_s: float, what: str) -> dict[str, Any]:
        """Helper ``i``'s answer (1-based), waiting at most ``timeout_s``."""
        conn, proc = self._conns[i - 1], self._procs[i - 1]
        deadline = time.monotonic() + timeout_s
        while not conn.poll(min(WAIT_S, max(0.0, deadline - time.monotonic()))):
            if not proc.is_alive():
                raise _Silent(f"band process {proc.name} ({what}) died, exit code "
                              f"{proc.exitcode}")
            if time.monotonic() >= deadline:
                raise _Silent(f"band process {proc.name} ({what}) did not answer "
                              f"within {timeout_s:g} s")
        try:
            reply: dict[str, Any] = json.loads(conn.recv_bytes())
        except (EOFError, OSError) as err:
            proc.join(1.0)  # its end of the pipe closes as it dies
            if not proc.is_alive():
                raise _Silent(f"band process {proc.name} ({what}) died, exit code "
                              f"{proc.exitcode}") from None
            raise _Silent(f"band process {proc.name} ({what}) closed its pipe: "
                          f"{err!r}") from None
        if "error" in reply:
            raise BandProcessFailed(f"band process {proc.name} ({what}): {reply['error']}\n"
                                    f"{reply.get('traceback', '')}")
        if "cpu_s" in reply:
            self._cpu[i - 1] = float(reply["cpu_s"])
        return reply

    def run_task(self, task: str, params: dict[str, Any],
                 bands: list[tuple[int, int]]) -> None:
        """Run ``task`` (:data:`sffscan.stages.volume_tasks.TASKS`) with ``params`` on every
        band, the first in this process; return when every band is done (and every task
        submitted before it: each helper runs its tasks in the order they came).

        Raises
        ------
        BandProcessFailed
            A helper raised (its error and traceback), died or took more than
            ``timeout_s``; the other bands are still waited for.
        """
        with self._lock:
            self._wait(self._submit(task, params, bands))

    def submit_task(self, task: str, params: dict[str, Any],
                    bands: list[tuple[int, int]]) -> int:
        """Start ``task`` on every band and return once the first band, this process's, is
        done, without waiting for the helpers: they run it after the tasks submitted before
        (in order, each on its own rows), while this process goes on. Returns the task's
        ticket for :meth:`wait_tasks`. Whatever the task reads in the shared arrays must
        not change, and what it writes must not be read here, until its ticket has been
        waited for. An error in a helper's band is raised by the wait that reaches it."""
        with self._lock:
            return self._submit(task, params, bands)

    def wait_tasks(self, ticket: int | None = None) -> None:
        """Wait until every helper has run the task of ``ticket`` (None: every task
        submitted); raise the first error one of them reported on the way."""
        with self._lock:
            self._wait(self._ticket if ticket is None else ticket)

    def _submit(self, task: str, params: dict[str, Any], bands: list[tuple[int, int]]) -> int:
        if len(bands) > self.k:
            raise ValueError(f"{len(bands)} bands for {self.k} band workers")
        if not self._conns and self.k > 1:
            raise BandProcessFailed(f"band processes '{self.name}' are closed")
        body = json.dumps(params, separators=(",", ":"))
        failure: BaseException | None = None
        self._ticket += 1
        for i, (a, b) in enumerate(bands[1:], start=1):
            try:
                self._conns[i - 1].send_bytes(
                    f'{{"task":"{task}","rows":[{a},{b}],"params":{body}}}'.encode())
                self._pending[i - 1].append((self._ticket, f"{task}, rows {a}..{b}"))
            except OSError as err:  # its end of the pipe is closed: it died
                proc = self._procs[i - 1]
                proc.join(1.0)
                failure = failure or BandProcessFailed(
                    f"band process {proc.name} ({task}, rows {a}..{b}) died, exit code "
                    f"{proc.exitcode} ({err})")
        if failure is None:
            try:
                run_task(self.arrays, task, params, bands[0])
            except BaseException as err:  # the helpers write into the same arrays: wait
                failure = err
        if failure is not None:
            with contextlib.suppress(BandProcessFailed):
                self._wait(self._ticket)
            raise failure
        return self._ticket

    def _wait(self, ticket: int) -> None:
        failure: BandProcessFailed | None = None
        for i, pending in enumerate(self._pending, start=1):
            while pending and pending[0][0] <= ticket:
                _, what = pending.popleft()
                try:
                    self._receive(i, self.timeout_s, what)
                except BandProcessFailed as err:
                    failure = failure or err
                    if isinstance(err, _Silent):
                        pending.clear()  # not one timeout a task it still had
        if failure is not None:
            raise failure

    def helpers_cpu_s(self) -> float:
        """CPU seconds the helpers have used since they were ready (as of their last
        answers; after :meth:`close`, all of it)."""
        return sum(self._cpu) - sum(self._cpu0)

    def _unlink(self) -> None:
        if not self._unlinked:
            self._unlinked = True
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()

    def close(self) -> None:
        """Stop and join the helpers, release the segment (idempotent; the tasks still
        running are waited for, their errors not raised)."""
        with contextlib.suppress(BandProcessFailed):
            self._wait(self._ticket)
        for pending in self._pending:
            pending.clear()
        for i, conn in enumerate(self._conns, start=1):
            with contextlib.suppress(OSError, BandProcessFailed):
                conn.send_bytes(b'{"task":"stop"}')
                self._receive(i, 5.0, "stop")
        join_or_kill((p.name, p) for p in self._procs)
        for conn in self._conns:
            conn.close()
        self._conns, self._procs = [], []
        self._unlink()
        self.arrays = {}  # the segment is unmapped when no array of it is left

    def __enter__(self) -> BandProcesses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LazyBandProcesses:
    """:class:`BandProcesses` started at the first use of :attr:`arrays` or
    :meth:`run_task` (in the process that runs the stages, not where they are built), shared
    by the stages that use them (the focus measure and depth stages); :meth:`close`,
    idempotent, stops them.

    Parameters
    ----------
    k, layout, **options
        :class:`BandProcesses`'s.
    """

    def __init__(self, k: int, layout: Layout, **options: Any) -> None:
        if k < 1:
            raise ValueError(f"k (band workers) must be >= 1, got {k}")
        self.k = k
        self.layout = layout
        self.options = options
        self._pool: BandProcesses | None = None
        self._closed = False
        self._cpu_s = 0.0  # the helpers' CPU once closed

    def _started(self) -> BandProcesses:
        if self._pool is None:
            if self._closed:
                raise BandProcessFailed("band processes used after they were closed")
            self._pool = BandProcesses(self.k, self.layout, **self.options)
        return self._pool

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        return self._started().arrays

    def run_task(self, task: str, params: dict[str, Any],
                 bands: list[tuple[int, int]]) -> None:
        self._started().run_task(task, params, bands)

    def submit_task(self, task: str, params: dict[str, Any],
                    bands: list[tuple[int, int]]) -> int:
        return self._started().submit_task(task, params, bands)

    def wait_tasks(self, ticket: int | None = None) -> None:
        if self._pool is not None:
            self._pool.wait_tasks(ticket)

    def helpers_cpu_s(self) -> float:
        """:meth:`BandProcesses.helpers_cpu_s` (kept once closed)."""
        return self._cpu_s if self._pool is None else self._pool.helpers_cpu_s()

    def close(self) -> None:
        self._closed = True
        if self._pool is not None:
            self._pool.close()
            self._cpu_s = self._pool.helpers_cpu_s()
            self._pool = None
