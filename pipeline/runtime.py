"""Stage runtime: concurrent stages joined by bounded queues.

Every stage runs in its own thread (numpy, OpenCV and torch release the GIL in their
kernels, so stages overlap on several cores), or, with ``one_thread``, the whole chain
runs in one thread, each item passed straight through every stage (for a worker process
whose stages would only take turns on one core anyway). Stages are joined by
:class:`~sffscan.pipeline.queues.BoundedQueue`, whose policy when full is declared
(``block`` by default; ``drop_oldest`` and ``drop_newest`` count every drop). Every put and
get waits with a timeout and re-checks the pipeline's stop flag between waits; nothing
sleeps to poll.

Side branches: a :class:`Sink` (the raw-stream recorder, the live viewer) receives the
outputs of the stages it names as :class:`Tapped` items through its own bounded queue, in
its own thread, with its own full policy (a viewer drops the oldest; a recorder blocks, and
the time the pipeline spent waiting for it is reported). Sinks get the end of stream after
the main chain has finished.

Shutdown: the source ends with :data:`END_OF_STREAM`; each stage drains its input, runs
its ``finish`` (flushing what it still holds), forwards the end-of-stream and stops. A stage
that raises stops the whole pipeline: the others leave at their next wait, every stage's
``close`` runs (so writers leave readable output), and :meth:`Pipeline.run` raises
:class:`StageFailed` with the stage's name and the cause.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import itertools
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol

from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads
from sffscan.pipeline.queues import BoundedQueue, PipelineStopped, offer_stats
from sffscan.pipeline.stats import (
    PipelineResult,
    StageStats,
    stats_snapshot,
)
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink, Stage, Tapped
from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def gc_frozen() -> Iterator[None]:
    """Keep the objects alive before streaming (the imported modules: torch, zarr, ...) out
    of the cyclic garbage collector's passes while streaming, then give them back.

    The head and tail threads and Zarr's I/O allocate many small containers, so full
    collections run every few frames, and each walked every object of the process: 0.3 ms
    of CPU per frame in the main process (perf, 1280 x 1024 default scan). Objects made
    while streaming are collected as usual; a cycle among the older ones that becomes
    garbage meanwhile is collected after the run.
    """
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


class PipelineCancelled(Exception):
    """:meth:`Pipeline.run` ended because :meth:`Pipeline.cancel` was called (another part
    of a multi-process pipeline failed or was interrupted); every stage was closed as
    failed."""


class StageFailed(RuntimeError):
    """A stage raised; the pipeline stopped. ``stage`` names it, ``__cause__`` is the error."""

    def __init__(self, stage: str, cause: BaseException) -> None:
        super().__init__(f"stage '{stage}' failed: {type(cause).__name__}: {cause}")
        self.stage = stage
        self.cause = cause


def _process_all(stage: Stage, item: Any) -> list[Any]:
    return list(stage.process(item))


class Placement(Protocol):
    """Where the stages of a :class:`Pipeline` run, when not each in a thread of this
    process (:class:`sffscan.pipeline.parallel.ProcessPlacement`)."""

    def run(self, pipeline: Pipeline) -> PipelineResult:
        """Run ``pipeline``'s stages and sinks so placed; as :meth:`Pipeline.run`."""
        ...


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
    sinks : list of Sink, optional
        Side branches fed from the outputs of the stages they tap, each by its own queue.
    placement : Placement, optional
        Where the stages run: None, each in a thread of this process; a
        :class:`~sffscan.pipeline.parallel.ProcessPlacement`, groups of them in worker
        processes (the same chain, sinks, statistics, end of stream and failures).
    one_thread : bool
        Run the whole chain in one thread: each output goes straight on through the next
        stages, with no queue between them (the sinks keep their threads and queues).
        For a process whose stages would only take turns on its core anyway
        (:func:`sffscan.pipeline.cores.one_thread_per_process`): threads that hand items
        over and contend for the interpreter's lock cost CPU there
        (``bench/bench_parallel.py --one-thread``). Same items, order, statistics, end of
        stream and failures; the queues between the stages count each hand-over as a put
        into an empty queue (fill 1).
    """

    def __init__(
        self,
        stages: list[Stage],
        *,
        capacity: int = 8,
        policies: dict[str, FullPolicy] | None = None,
        on_progress: Callable[[list[StageStats], float], None] | None = None,
        progress_s: float = 1.0,
        sinks: list[Sink] | None = None,
        stop: threading.Event | None = None,
        placement: Placement | None = None,
        one_thread: bool = False,
    ) -> None:
        if not stages:
            raise ValueError("a pipeline needs at least a source stage")
        self.sinks = list(sinks or [])
        names = [s.name for s in stages]
        all_names = names + [k.name for k in self.sinks]
        if len(set(all_names)) != len(all_names):
            raise ValueError(f"stage and sink names must be unique, got {all_names}")
        for k in self.sinks:
            unknown = set(k.taps) - set(names)
            if unknown:
                raise ValueError(f"sink '{k.name}' taps unknown stages {sorted(unknown)}")
        self.stages = stages
        self.capacity = capacity
        self.placement = placement
        self.one_thread = one_thread
        self.prepared = False  # Stage.prepare done (see prepare)
        self.stop = stop if stop is not None else threading.Event()
        self.cancelled = False
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
        self.sink_queues = [BoundedQueue(f"{'+'.join(k.taps) or 'stats'}->{k.name}", k.capacity,
                                         policy=k.policy, stop=self.stop, precious=k.precious,
                                         precious_wait=k.precious_wait)
                            for k in self.sinks]
        self.sink_stats = [StageStats(k.name, k.unit) for k in self.sinks]
        #: for each main stage, the queues of the sinks that tap it
        self._taps: list[list[BoundedQueue]] = [
            [q for k, q in zip(self.sinks, self.sink_queues, strict=True) if s.name in k.taps]
            for s in stages
        ]
        #: seconds each stage spent waiting for a blocking sink queue (a sink falling behind)
        self.sink_wait_s: dict[str, float] = {k.name: 0.0 for k in self.sinks}
        self.on_progress = on_progress
        self.progress_s = progress_s
        self._errors: list[tuple[str, BaseException]] = []
        self._lock = threading.Lock()

    def _emit(self, index: int, outputs: Iterable[Any]) -> None:
        out_q = self.queues[index] if index < len(self.queues) else None
        for out in outputs:
            self._tap(index, out)
            if out_q is not None:
                out_q.put(out)

    def _tap(self, index: int, out: Any) -> None:
        """Count an output of stage ``index`` and hand it to the sinks that tap the stage."""
        self.stats[index].items_out += 1
        name = self.stages[index].name
        for q in self._taps[index]:
            t0 = time.perf_counter()
            q.put(Tapped(name, out))
            waited = time.perf_counter() - t0
            if waited > 1e-3 and q.policy is FullPolicy.BLOCK:
                with self._lock:
                    sink = q.name.rsplit("->", 1)[1]
                    self.sink_wait_s[sink] += waited

    def _run_stage(self, index: int) -> None:
        out_q = self.queues[index] if index < len(self.queues) else None
        self._drive(self.stages[index], self.stats[index],
                    self.queues[index - 1] if index > 0 else None,
                    lambda outputs: self._emit(index, outputs), out_q)

    def _run_sink(self, index: int) -> None:
        self._drive(self.sinks[index], self.sink_stats[index], self.sink_queues[index],
                    lambda outputs: None, None)

    def _drive(self, stage: Stage, stats: StageStats, in_q: BoundedQueue | None,
               emit: Callable[[list[Any]], None], out_q: BoundedQueue | None) -> None:
        """Run a stage (a source when ``in_q`` is None) or a sink to the end of its stream,
        timing its own code; a failure is recorded with its name and stops the pipeline."""

        def timed(call: Callable[[], list[Any]]) -> list[Any]:
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return call()
            finally:
                stats.busy_s += time.perf_counter() - t0
                stats.cpu_s += time.thread_time() - c0

        try:
            if in_q is None:
                it = iter(stage.produce())
                while not self.stop.is_set():
                    produced = timed(lambda: list(itertools.islice(it, 1)))
                    if not produced:
                        break
                    stats.frames += 1
                    emit(produced)
            else:
                while True:
                    item = in_q.get()
                    if item is END_OF_STREAM:
                        break
                    stats.items_in += 1
                    outputs = timed(functools.partial(_process_all, stage, item))
                    stats.frames += 1
                    emit(outputs)
            emit(timed(lambda: list(stage.finish())))
            if out_q is not None:
                out_q.put(END_OF_STREAM)
        except PipelineStopped:
            return
        except BaseException as exc:  # noqa: BLE001 - reported with the stage's name
            with self._lock:
                self._errors.append((stage.name, exc))
            self.stop.set()

    def _run_chain(self) -> None:
        """The chain in this one thread (``one_thread``): the source's items, each passed
        through every later stage before the next is taken; then each stage's ``finish``,
        in order, its outputs passed on alike. A failure is recorded with the name of the
        stage that raised and stops the pipeline, as in :meth:`_drive`."""
        stages, stats = self.stages, self.stats
        failed: list[int] = []  # the stage whose call raised

        def timed(index: int, call: Callable[[], list[Any]]) -> list[Any]:
            st = stats[index]
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return call()
            except PipelineStopped:
                raise
            except BaseException:
                failed.append(index)
                raise
            finally:
                st.busy_s += time.perf_counter() - t0
                st.cpu_s += time.thread_time() - c0

        def handed(index: int) -> None:
            # the queue after stage ``index`` as a hand-over: an item put into it is taken
            # at once, so it holds one at each put (the end of stream counted, as a put)
            q = self.queues[index].stats
            q.puts += 1
            q.fill_sum += 1
            q.max_fill = max(q.max_fill, 1)

        def push(index: int, outputs: list[Any]) -> None:
            for out in outputs:
                self._tap(index, out)
                nxt = index + 1
                if nxt < len(stages):
                    handed(index)
                    stats[nxt].items_in += 1
                    more = timed(nxt, functools.partial(_process_all, stages[nxt], out))
                    stats[nxt].frames += 1
                    push(nxt, more)

        try:
            it = iter(stages[0].produce())
            while not self.stop.is_set():
                produced = timed(0, lambda: list(itertools.islice(it, 1)))
                if not produced:
                    break
                stats[0].frames += 1
                push(0, produced)
            if self.stop.is_set():  # stopped (cancelled, or a sink failed): no flushing
                return
            for i, stage in enumerate(stages):
                push(i, timed(i, lambda stage=stage: list(stage.finish())))  # type: ignore[misc]
                if i < len(self.queues):
                    handed(i)  # the end of stream
        except PipelineStopped:
            return
        except BaseException as exc:  # noqa: BLE001 - reported with the stage's name
            name = stages[failed[-1]].name if failed else stages[0].name
            with self._lock:
                self._errors.append((name, exc))
            self.stop.set()

    def cancel(self) -> None:
        """Stop every stage at its next wait; :meth:`run` closes them as failed and raises
        :class:`PipelineCancelled` (unless a stage failed: then :class:`StageFailed`)."""
        self.cancelled = True
        self.stop.set()

    def _snapshot(self, elapsed: float, *, last: bool = False) -> None:
        snap = stats_snapshot(elapsed, self.stats + self.sink_stats,
                              (q.stats for q in self.queues + self.sink_queues))
        for k, q in zip(self.sinks, self.sink_queues, strict=True):
            offer_stats(k, q, snap, last=last)

    def run(self, *, freeze_gc: bool = True, limit_opencv: bool = True) -> PipelineResult:
        """Run to the end of the stream; raise :class:`StageFailed` if a stage failed.

        While it runs, BLAS is limited to one thread: the stages already run in parallel,
        and OpenBLAS's idle threads spin after each small call (the registration's solve),
        which cost 9 ms of CPU per frame on 2 cores (measured: 66 -> 89 frames/s). With
        ``freeze_gc`` the objects that exist before streaming are kept out of the garbage
        collector's passes meanwhile (:func:`gc_frozen`); a caller that runs several
        pipelines at once freezes once around them all and passes False. With
        ``limit_opencv`` OpenCV runs one thread of its own where the machine has no more
        cores than stages (:mod:`sffscan.pipeline.opencv_threads`); the process placement
        decides for its processes and passes False for the pipelines inside them.
        """
        if self.placement is not None:
            return self.placement.run(self)
        with threadpool_limits(limits=1, user_api="blas"), \
                opencv_thread_limit(opencv_threads(len(self.stages)) if limit_opencv
                                    else None), \
                gc_frozen() if freeze_gc else contextlib.nullcontext():
            return self._run()

    def prepare(self) -> None:
        """Every stage's :meth:`Stage.prepare`, once (a worker calls it before it reports
        ready, :meth:`run` otherwise); :class:`StageFailed` names a stage that could not
        (nothing has run yet: the stages are closed as failed)."""
        if self.prepared:
            return
        self.prepared = True
        for stage in self.stages:
            try:
                stage.prepare()
            except Exception as exc:  # noqa: BLE001 - re-raised with the stage's name
                for s in self.stages:
                    with contextlib.suppress(Exception):  # the first failure is the one told
                        s.close(failed=True)
                raise StageFailed(stage.name, exc) from exc

    def _run(self) -> PipelineResult:
        self.prepare()
        t_start = time.perf_counter()
        threads = [
            threading.Thread(target=self._run_stage, args=(i,), name=f"stage-{s.name}", daemon=True)
            for i, s in enumerate(self.stages)
        ] if not self.one_thread else [
            threading.Thread(target=self._run_chain, name="stages", daemon=True)]
        sink_threads = [
            threading.Thread(target=self._run_sink, args=(i,), name=f"sink-{k.name}", daemon=True)
            for i, k in enumerate(self.sinks)
        ]
        for t in threads + sink_threads:
            t.start()
        try:
            last = threads[-1]
            while last.is_alive():
                last.join(self.progress_s)
                if last.is_alive():
                    elapsed = time.perf_counter() - t_start
                    if self.on_progress is not None:
                        self.on_progress(self.stats, elapsed)
                    self._snapshot(elapsed)
            if not self.stop.is_set():
                self._snapshot(time.perf_counter() - t_start, last=True)
                for q in self.sink_queues:  # the sinks drain what they hold, then end
                    q.put(END_OF_STREAM)
                for t in sink_threads:
                    t.join()
            self.stop.set()  # anything upstream still waiting leaves now
            for t in threads + sink_threads:
                t.join()
        except BaseException:  # Ctrl-C, or the progress display failing: stop cleanly
            self.stop.set()
            for t in threads + sink_threads:
                t.join()
            self._close_all(failed=True)
            raise
        failed = bool(self._errors) or self.cancelled
        close_error = self._close_all(failed=failed)
        if self._errors:
            name, exc = self._errors[0]
            raise StageFailed(name, exc) from exc
        if self.cancelled:
            raise PipelineCancelled()
        if close_error is not None:
            raise StageFailed(*close_error) from close_error[1]
        extras = {s.name: s.extra_stats() for s in self.stages + self.sinks}
        for name, waited in self.sink_wait_s.items():
            extras[name] = {**extras[name], "pipeline_waited_s": round(waited, 3)}
        return PipelineResult(
            wall_s=time.perf_counter() - t_start,
            stages=self.stats + self.sink_stats,
            queues=[q.stats for q in self.queues + self.sink_queues],
            extras=extras,
            sinks=tuple(k.name for k in self.sinks),
        )

    def _close_all(self, *, failed: bool) -> tuple[str, BaseException] | None:
        first: tuple[str, BaseException] | None = None
        for stage in self.stages + self.sinks:
            try:
                stage.close(failed=failed)
            except Exception as exc:  # noqa: BLE001 - every stage gets its close
                if first is None:
                    first = (stage.name, exc)
        return first
