"""Stage runtime: concurrent stages joined by bounded queues.

Every stage runs in its own thread (numpy, OpenCV and torch release the GIL in their
kernels, so stages overlap on several cores). Stages are joined by :class:`BoundedQueue`,
whose policy when full is declared (``block`` by default; ``drop_oldest`` and
``drop_newest`` count every drop). Every put and get waits with a timeout and re-checks
the pipeline's stop flag between waits; nothing sleeps to poll.

Shutdown: the source ends with :data:`END_OF_STREAM`; each stage drains its input, runs
its ``finish`` (flushing what it still holds), forwards the end-of-stream and stops. A stage
that raises stops the whole pipeline: the others leave at their next wait, every stage's
``close`` runs (so writers leave readable output), and :meth:`Pipeline.run` raises
:class:`StageFailed` with the stage's name and the cause.
"""

from __future__ import annotations

import collections
import enum
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from threadpoolctl import threadpool_limits


class EndOfStream:
    """The end-of-stream marker; use the single instance :data:`END_OF_STREAM`."""

    def __repr__(self) -> str:
        return "END_OF_STREAM"


END_OF_STREAM = EndOfStream()


class FullPolicy(enum.StrEnum):
    """What a queue does when it is full."""

    BLOCK = "block"
    DROP_OLDEST = "drop_oldest"
    DROP_NEWEST = "drop_newest"


class PipelineStopped(Exception):
    """Raised inside a stage's wait when another stage has failed."""


class StageFailed(RuntimeError):
    """A stage raised; the pipeline stopped. ``stage`` names it, ``__cause__`` is the error."""

    def __init__(self, stage: str, cause: BaseException) -> None:
        super().__init__(f"stage '{stage}' failed: {type(cause).__name__}: {cause}")
        self.stage = stage
        self.cause = cause


@dataclass
class QueueStats:
    name: str
    capacity: int
    policy: str
    puts: int = 0
    dropped: int = 0
    max_fill: int = 0
    fill_sum: int = 0

    @property
    def mean_fill(self) -> float:
        return self.fill_sum / self.puts if self.puts else 0.0


class BoundedQueue:
    """A bounded FIFO between two stages with a declared full policy.

    Parameters
    ----------
    name : str
        Shown in statistics and errors.
    capacity : int
        Maximum number of items held (>= 1).
    policy : FullPolicy
        ``block`` waits for room; ``drop_oldest`` discards the oldest item, ``drop_newest``
        discards the new one. Drops are counted. The end-of-stream marker is never dropped.
    wait_s : float
        Longest single wait before the stop flag is checked again.
    """

    def __init__(
        self,
        name: str,
        capacity: int,
        *,
        policy: FullPolicy = FullPolicy.BLOCK,
        stop: threading.Event | None = None,
        wait_s: float = 0.25,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"queue '{name}': capacity must be >= 1, got {capacity}")
        self.name = name
        self.capacity = capacity
        self.policy = FullPolicy(policy)
        self.stop = stop if stop is not None else threading.Event()
        self.wait_s = wait_s
        self._items: collections.deque[Any] = collections.deque()
        self._cond = threading.Condition()
        self.stats = QueueStats(name, capacity, self.policy.value)

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: Any) -> None:
        with self._cond:
            full = len(self._items) >= self.capacity
            if full and item is not END_OF_STREAM and self.policy is FullPolicy.DROP_NEWEST:
                self.stats.dropped += 1
                return
            if full and item is not END_OF_STREAM and self.policy is FullPolicy.DROP_OLDEST:
                self._items.popleft()  # the end of stream is the last item ever put
                self.stats.dropped += 1
            # block (and the end of stream under any policy): wait for room
            while len(self._items) >= self.capacity:
                if self.stop.is_set():
                    raise PipelineStopped(self.name)
                self._cond.wait(self.wait_s)
            self._items.append(item)
            self.stats.puts += 1
            fill = len(self._items)
            self.stats.fill_sum += fill
            self.stats.max_fill = max(self.stats.max_fill, fill)
            self._cond.notify_all()

    def get(self) -> Any:
        with self._cond:
            while not self._items:
                if self.stop.is_set():
                    raise PipelineStopped(self.name)
                self._cond.wait(self.wait_s)
            item = self._items.popleft()
            self._cond.notify_all()
            return item


@dataclass
class StageStats:
    name: str
    unit: str = "frames"
    items_in: int = 0
    items_out: int = 0
    frames: int = 0  # input items handled (frames for most stages; see ``unit``)
    busy_s: float = 0.0  # wall time inside the stage's own code
    cpu_s: float = 0.0  # CPU time of the stage's thread inside its own code

    @property
    def frames_per_s(self) -> float:
        """Items handled per second of this stage's own busy time."""
        return self.frames / self.busy_s if self.busy_s > 0 else 0.0


class Stage:
    """Base class of a pipeline stage.

    Subclasses implement :meth:`process` (one input item to zero or more outputs) and may
    implement :meth:`finish` (flush at end of stream) and :meth:`close` (release resources;
    ``failed`` tells whether the pipeline is stopping on an error). A source implements
    :meth:`produce` instead of :meth:`process`.
    """

    name = "stage"
    #: What one input item of this stage is, for the statistics ("frames", "blocks").
    unit = "frames"

    def process(self, item: Any) -> Iterable[Any]:
        raise NotImplementedError

    def produce(self) -> Iterator[Any]:
        raise NotImplementedError

    def finish(self) -> Iterable[Any]:
        return ()

    def close(self, *, failed: bool) -> None:
        return None

    def extra_stats(self) -> dict[str, Any]:
        """Stage-specific figures for the summary (dropped frames, corrections, ...)."""
        return {}


@dataclass
class PipelineResult:
    wall_s: float
    stages: list[StageStats]
    queues: list[QueueStats]
    extras: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def dropped(self) -> int:
        return sum(q.dropped for q in self.queues)


class Pipeline:
    """A linear chain of stages: ``stages[0]`` is the source, each feeds the next.

    Parameters
    ----------
    stages : list of Stage
    capacity : int
        Capacity of each queue between stages.
    policies : dict, optional
        Full policy per queue, keyed by the name of the stage the queue feeds.
    on_progress : callable, optional
        Called from the runner thread about every ``progress_s`` seconds with the stage
        statistics, for progress display.
    """

    def __init__(
        self,
        stages: list[Stage],
        *,
        capacity: int = 8,
        policies: dict[str, FullPolicy] | None = None,
        on_progress: Callable[[list[StageStats], float], None] | None = None,
        progress_s: float = 1.0,
    ) -> None:
        if not stages:
            raise ValueError("a pipeline needs at least a source stage")
        names = [s.name for s in stages]
        if len(set(names)) != len(names):
            raise ValueError(f"stage names must be unique, got {names}")
        self.stages = stages
        self.stop = threading.Event()
        policies = policies or {}
        self.queues = [
            BoundedQueue(
                f"{a.name}->{b.name}",
                capacity,
                policy=policies.get(b.name, FullPolicy.BLOCK),
                stop=self.stop,
            )
            for a, b in zip(stages[:-1], stages[1:], strict=True)
        ]
        self.stats = [StageStats(s.name, s.unit) for s in stages]
        self.on_progress = on_progress
        self.progress_s = progress_s
        self._errors: list[tuple[str, BaseException]] = []
        self._lock = threading.Lock()

    def _emit(self, index: int, outputs: Iterable[Any]) -> None:
        stats = self.stats[index]
        out_q = self.queues[index] if index < len(self.queues) else None
        for out in outputs:
            stats.items_out += 1
            if out_q is not None:
                out_q.put(out)

    def _run_stage(self, index: int) -> None:
        stage, stats = self.stages[index], self.stats[index]
        try:
            if index == 0:
                it = iter(stage.produce())
                while not self.stop.is_set():
                    t0, c0 = time.perf_counter(), time.thread_time()
                    try:
                        item = next(it)
                    except StopIteration:
                        break
                    stats.busy_s += time.perf_counter() - t0
                    stats.cpu_s += time.thread_time() - c0
                    stats.frames += 1
                    self._emit(index, (item,))
            else:
                in_q = self.queues[index - 1]
                while True:
                    item = in_q.get()
                    if item is END_OF_STREAM:
                        break
                    stats.items_in += 1
                    t0, c0 = time.perf_counter(), time.thread_time()
                    outputs = list(stage.process(item))
                    stats.busy_s += time.perf_counter() - t0
                    stats.cpu_s += time.thread_time() - c0
                    stats.frames += 1
                    self._emit(index, outputs)
            t0, c0 = time.perf_counter(), time.thread_time()
            tail = list(stage.finish())
            stats.busy_s += time.perf_counter() - t0
            stats.cpu_s += time.thread_time() - c0
            self._emit(index, tail)
            if index < len(self.queues):
                self.queues[index].put(END_OF_STREAM)
        except PipelineStopped:
            return
        except BaseException as exc:  # noqa: BLE001 - reported with the stage's name
            with self._lock:
                self._errors.append((stage.name, exc))
            self.stop.set()

    def run(self) -> PipelineResult:
        """Run to the end of the stream; raise :class:`StageFailed` if a stage failed.

        While it runs, BLAS is limited to one thread: the stages already run in parallel,
        and OpenBLAS's idle threads spin after each small call (the registration's solve),
        which cost 9 ms of CPU per frame on 2 cores (measured: 66 -> 89 frames/s).
        """
        with threadpool_limits(limits=1, user_api="blas"):
            return self._run()

    def _run(self) -> PipelineResult:
        t_start = time.perf_counter()
        threads = [
            threading.Thread(target=self._run_stage, args=(i,), name=f"stage-{s.name}", daemon=True)
            for i, s in enumerate(self.stages)
        ]
        for t in threads:
            t.start()
        try:
            last = threads[-1]
            while last.is_alive():
                last.join(self.progress_s)
                if self.on_progress is not None and last.is_alive():
                    self.on_progress(self.stats, time.perf_counter() - t_start)
            self.stop.set()  # anything upstream still waiting leaves now
            for t in threads:
                t.join()
        except BaseException:  # Ctrl-C, or the progress display failing: stop cleanly
            self.stop.set()
            for t in threads:
                t.join()
            self._close_all(failed=True)
            raise
        failed = bool(self._errors)
        close_error = self._close_all(failed=failed)
        if self._errors:
            name, exc = self._errors[0]
            raise StageFailed(name, exc) from exc
        if close_error is not None:
            raise StageFailed(*close_error) from close_error[1]
        return PipelineResult(
            wall_s=time.perf_counter() - t_start,
            stages=self.stats,
            queues=[q.stats for q in self.queues],
            extras={s.name: s.extra_stats() for s in self.stages},
        )

    def _close_all(self, *, failed: bool) -> tuple[str, BaseException] | None:
        first: tuple[str, BaseException] | None = None
        for stage in self.stages:
            try:
                stage.close(failed=failed)
            except Exception as exc:  # noqa: BLE001 - every stage gets its close
                if first is None:
                    first = (stage.name, exc)
        return first
