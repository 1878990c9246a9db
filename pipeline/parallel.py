"""The process placement: groups of a pipeline's stages in worker processes, frames in
shared memory (``Pipeline(stages, placement=ProcessPlacement(...))``).

    main process                 worker "registration"        worker "focus"             main
    source -> speed_shift -> ch1 -> registration -> ch2 -> focus_measure -> depth -> ch3 -> mosaic
           \\-> ForwardSink -> ch4 -> recorder (own process)
    viewer (main) <- ch5 <- forwarders where registration, focus_measure, depth run (relay)

Each worker runs its group of stages with the thread runtime (:class:`Pipeline`), between a
:class:`~sffscan.pipeline.channels.RecvStage` and a
:class:`~sffscan.pipeline.channels.SendStage`; the main process runs the head (the source)
and the tail (the mosaic writer, which owns the output) the same way. Workers are started
with the ``spawn`` context (no fork of a process with torch or OpenCV threads) and build
their stages themselves by a module-level factory function (which travels by its name) and
JSON arguments (the scan configuration): no stage and no pixel is pickled.

Correctness rules kept from the thread runtime:

- a stage that raises, in any process, stops every process: the worker reports the stage
  and the cause (type, message) to the main process, which sends a stop order down a pipe
  to every worker; every other chain leaves at its next wait, every stage's ``close``
  runs (the mosaic is marked 'failed' and stays readable) and :meth:`ProcessPipeline.run` raises
  :class:`StageFailed` with that name and cause;
- Ctrl-C: workers ignore SIGINT; the main process sends the stop order, closes its
  stages, joins the workers (then terminates what is left) and re-raises;
- ``kill -9`` of the main process: each worker asked the kernel for SIGKILL when its
  parent dies (``PR_SET_PDEATHSIG``) and also leaves when its stop pipe reaches end of
  file or ``os.getppid()`` changes;
  the shared-memory segments were unlinked as soon as the workers had attached, so
  nothing is left in ``/dev/shm``.

Sinks of the main process (the live viewer) may tap stages of the workers: each process
that runs some of a sink's taps forwards their outputs (placed frames by reference into the
frame ring, no copy; other arrays into a slot) through one channel to the main process,
where the sink runs behind its own queue and policy, as in the thread runtime (a relay,
:mod:`sffscan.pipeline.relays`). The main process sends the sink the pipeline's statistics
too (``wants_stats``), the last ones after every worker has reported, then the end of
stream.

Memory is bounded by the pools: ``sum(slots * slot_bytes)``, fixed at start (see
:func:`sffscan.pipeline.scan_processes.ring_plan` for the scan pipeline's formula).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from sffscan.pipeline.channels import (
    ForwardSink,
    PooledSource,
    RecvStage,
    SendStage,
)
from sffscan.pipeline.cores import one_thread_per_process
from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads
from sffscan.pipeline.process_figures import chain_queues, live_stages, process_result
from sffscan.pipeline.relays import AfterRelays, Relay, RelayRun, relay_of, relayed_sinks
from sffscan.pipeline.runtime import Pipeline, StageFailed, gc_frozen
from sffscan.pipeline.shm_ring import SlotPool, new_spec
from sffscan.pipeline.spawn import (
    START_TIMEOUT_S,
    StopPipes,
    join_or_kill,
    spawn_context,
)
from sffscan.pipeline.stats import PipelineResult, StageStats
from sffscan.pipeline.worker import (
    INNER_CAPACITY,
    HostedSink,
    WorkerGroup,
    rebuild_exception,
    worker_main,
)
from sffscan.stages.protocol import FullPolicy, Sink, Stage

log = logging.getLogger(__name__)


@dataclass
class _Worker:
    label: str
    proc: Any
    stages: tuple[str, ...]
    report: dict[str, Any] | None = None
    ready: bool = False


def _reports(workers: list[_Worker]) -> list[dict[str, Any]]:
    """The workers' reports (an empty dict for one not in yet)."""
    return [w.report or {} for w in workers]


@dataclass
class ProcessPlacement:
    """The process placement of a :class:`~sffscan.pipeline.runtime.Pipeline`'s stages
    (its ``placement``): each of ``groups`` names consecutive stages run in one worker
    process, which builds its own (so the pipeline's objects for them are not run); the
    stages before the first group (the source among them) and after the last run in the
    main process, with the sinks that are not ``hosted`` in their own process; ``pools``:
    the shared memory (:class:`ProcessPipeline`)."""

    groups: list[WorkerGroup]
    pools: list[tuple[str, int, int, tuple[str, ...]]]
    hosted: list[HostedSink] = field(default_factory=list)

    def run(self, pipeline: Pipeline) -> PipelineResult:
        names = [s.name for s in pipeline.stages]
        placed = [n for g in self.groups for n in g.stages]
        first = names.index(placed[0]) if placed and placed[0] in names else -1
        if first < 1 or names[first:first + len(placed)] != placed:
            raise ValueError(f"the worker groups' stages {placed} are not consecutive stages "
                             f"after the source in {names}")
        dropping = [q.name for q in pipeline.queues if q.policy is not FullPolicy.BLOCK]
        if dropping:
            raise ValueError(f"the process placement runs blocking queues only, not {dropping}")
        hosted = {k.name for k in self.hosted}
        return ProcessPipeline(
            head=pipeline.stages[:first], groups=self.groups,
            tail=pipeline.stages[first + len(placed):], pools=self.pools,
            capacity=pipeline.capacity, hosted=self.hosted,
            sinks=[k for k in pipeline.sinks if k.name not in hosted],
            on_progress=pipeline.on_progress, progress_s=pipeline.progress_s).run()


@dataclass
class ProcessPipeline:
    """head (main) -> groups (one worker process each) -> tail (main), plus sinks: what
    runs a :class:`ProcessPlacement`.

    Parameters
    ----------
    head, tail : list of Stage
        Run in the main process: ``head[0]`` is the source; ``tail`` gets the last group's
        output (it may own files that must be closed here, like the mosaic writer).
    groups : list of WorkerGroup
        The chain's middle, one worker process each, in order.
    pools : list of (label, slots, slot_bytes, kinds)
        Shared-memory pools; an array that is not in a pool yet goes into the smallest
        slot it fits of a pool taking its message type (``kinds``: "frame", "placed",
        "focus", "block"). The first pool must take "frame": the source's frames are
        written into it once and passed on by reference.
    capacity : int
        Messages each channel between processes holds.
    sinks : list of Sink
        Local sinks (threads of the main process). One that taps only head stages, or
        only tail stages, is fed like in the thread runtime; any other is relayed: the
        processes that run its taps forward their outputs through one channel (module
        docstring; :func:`~sffscan.pipeline.relays.relay_of`).
    hosted : list of HostedSink
        Sinks in their own process tapping head stages.
    """

    head: list[Stage]
    groups: list[WorkerGroup]
    tail: list[Stage]
    pools: list[tuple[str, int, int, tuple[str, ...]]]
    capacity: int = 8
    sinks: list[Sink] = field(default_factory=list)
    hosted: list[HostedSink] = field(default_factory=list)
    on_progress: Callable[[list[StageStats], float], None] | None = None
    progress_s: float = 1.0
    #: each stage worker runs its stages in one thread (``Pipeline``'s ``one_thread``);
    #: None: where the machine has no more cores than the placement has processes
    #: (:func:`~sffscan.pipeline.cores.one_thread_per_process`)
    one_thread: bool | None = None

    def run(self) -> PipelineResult:
        """Run to the end of the stream (:meth:`Pipeline.run`'s contract). OpenCV runs one
        thread of its own in every process where the machine has no more cores than the
        placement has processes (:mod:`sffscan.pipeline.opencv_threads`), and so do the
        stage workers' stages (:attr:`one_thread`)."""
        processes = 1 + len(self.groups) + len(self.hosted)
        cv_threads = opencv_threads(processes)
        one = one_thread_per_process(processes) if self.one_thread is None else self.one_thread
        with opencv_thread_limit(cv_threads):
            return self._run_processes(cv_threads, one)

    def _run_processes(self, cv_threads: int | None, one_thread: bool) -> PipelineResult:
        ctx = spawn_context()
        specs = [new_spec(label, slots=n, slot_bytes=b, kinds=k) for label, n, b, k in self.pools]
        syncs = [(ctx.Lock(), ctx.Semaphore(s.slots)) for s in specs]
        pools: list[SlotPool] = []
        workers: list[_Worker] = []
        abort = StopPipes()
        results = ctx.Queue()
        stop = threading.Event()
        t_start = time.perf_counter()  # wall_s counts from the workers' readiness
        try:
            for s, sync in zip(specs, syncs, strict=True):
                pools.append(SlotPool(s, sync, create=True))
            chans = [ctx.Queue(self.capacity) for _ in range(len(self.groups) + 1)]
            sink_qs = [ctx.Queue(k.capacity) for k in self.hosted]
            relays = [relay_of(k) for k in self._relayed()]
            relay_qs = [ctx.Queue(r.capacity + r.reserve) for r in relays]
            pj = [s.to_json() for s in specs]
            for i, g in enumerate(self.groups):
                spec = {"label": g.label, "factory": g.factory, "kwargs": g.kwargs,
                        "capacity": self.capacity, "opencv_threads": cv_threads,
                        "one_thread": one_thread}
                mine = [(r, q) for r, q in zip(relays, relay_qs, strict=True)
                        if set(r.taps) & set(g.stages)]
                p = ctx.Process(target=worker_main, name=f"sffscan-{g.label}",
                                args=(spec, "stages", pj, syncs, chans[i], chans[i + 1],
                                      results, abort.pipe(ctx), os.getpid(), 1, mine),
                                daemon=not g.spawns)
                workers.append(_Worker(g.label, p, g.stages))
            for k, q in zip(self.hosted, sink_qs, strict=True):
                spec = {"label": k.name, "factory": k.factory, "kwargs": k.kwargs,
                        "opencv_threads": cv_threads}
                p = ctx.Process(target=worker_main, name=f"sffscan-{k.name}",
                                args=(spec, "sink", pj, syncs, q, None, results,
                                      abort.pipe(ctx), os.getpid()), daemon=True)
                workers.append(_Worker(k.name, p, (k.name,)))
            for w in workers:
                w.proc.start()
            abort.started()
            self._await_ready(workers, results)
            for pool in pools:  # every process has mapped them: no name is left behind
                pool.unlink()
            startup_s = time.perf_counter() - t_start
            cpu0 = time.process_time()
            with gc_frozen():
                result = self._run(pools, workers, chans, sink_qs, results, abort, stop,
                                   time.perf_counter(), list(zip(relays, relay_qs,
                                                                 strict=True)))
            cpu = time.process_time() - cpu0 + sum((w.report or {}).get("cpu_s", 0.0)
                                                   for w in workers)
            result.extras["processes"] = {"workers": len(workers),
                                          "startup_s": round(startup_s, 2),
                                          "cpu_s": round(cpu, 3),
                                          "shared_memory_MB": round(sum(
                                              s.total_bytes for s in specs) / 1e6, 1)}
            return result
        except BaseException:
            abort.set()
            stop.set()
            raise
        finally:
            abort.set()
            join_or_kill((w.label, w.proc) for w in workers)
            abort.close()
            for pool in pools:
                pool.close()

    # -- start and stop ------------------------------------------------------------------
    def _await_ready(self, workers: list[_Worker], results: Any) -> None:
        t0 = time.monotonic()
        while not all(w.ready for w in workers):
            self._poll(workers, results, timeout=0.25)
            for w in workers:
                if w.report is not None and w.report["kind"] == "error":
                    raise StageFailed(w.report["stage"], rebuild_exception(w.report))
                if not w.ready and not w.proc.is_alive():
                    raise StageFailed(w.label, RuntimeError(
                        f"worker process exited with code {w.proc.exitcode} while starting"))
            if time.monotonic() - t0 > START_TIMEOUT_S:
                raise StageFailed(workers[0].label, TimeoutError(
                    f"worker processes not ready after {START_TIMEOUT_S:g} s"))

    @staticmethod
    def _poll(workers: list[_Worker], results: Any, *, timeout: float,
              drain: bool = False) -> None:
        """Wait up to ``timeout`` for the workers' messages; return as soon as one came
        (and those already queued behind it are taken): the caller's loop checks the end
        of the run after each, so waiting out the timeout would hold the end (and the
        wall time) up to ``timeout`` longer. ``drain``: take every message until the
        timeout (after a stop, so that each worker's report is in)."""
        deadline = time.monotonic() + timeout
        wait = timeout
        while True:
            try:
                msg = json.loads(results.get(timeout=wait) if wait > 0
                                 else results.get_nowait())
            except Exception:  # noqa: BLE001 - queue.Empty: nothing more for now
                return
            wait = max(0.0, deadline - time.monotonic()) if drain else 0.0
            for w in workers:
                if w.label == msg["label"]:
                    if msg["kind"] == "ready":
                        w.ready = True
                    elif w.report is None or w.report["kind"] != "error":
                        w.report = msg

    # -- run -----------------------------------------------------------------------------
    def _relayed(self) -> list[Sink]:
        return relayed_sinks(self.sinks, [s.name for s in self.head],
                             [s.name for s in self.tail])

    def _run(self, pools: list[SlotPool], workers: list[_Worker], chans: list[Any],
             sink_qs: list[Any], results: Any, abort: StopPipes, stop: threading.Event,
             t_start: float, relays: list[tuple[Relay, Any]]) -> PipelineResult:
        head_names = {s.name for s in self.head}
        tail_names = {s.name for s in self.tail}
        for k in self.hosted:
            if not set(k.taps) <= head_names:
                raise ValueError(f"hosted sink '{k.name}' may tap only the main process's "
                                 f"head stages {sorted(head_names)}")
        known = head_names | tail_names | {n for g in self.groups for n in g.stages}
        for sink in self.sinks:
            if not set(sink.taps) <= known:
                raise ValueError(f"sink '{sink.name}' taps unknown stages "
                                 f"{sorted(set(sink.taps) - known)}")
        # each local chain has its own stop flag: a chain that ends sets it
        head_stop, tail_stop = stop, threading.Event()
        forwards = [
            ForwardSink(k.name, k.taps, q, capacity=k.capacity, policy=k.policy, pools=pools,
                        stop=head_stop) for k, q in zip(self.hosted, sink_qs, strict=True)]
        relayed = {r.name for r, _ in relays}
        head_sinks = [k for k in self.sinks if set(k.taps) <= head_names
                      and k.name not in relayed]
        tail_sinks = [k for k in self.sinks if k not in head_sinks and k.name not in relayed]
        relay_runs = [RelayRun(r, q, next(k for k in self.sinks if k.name == r.name), pools,
                                head_names, tail_names, head_stop, tail_stop,
                                sum(1 for g in self.groups if set(r.taps) & set(g.stages)))
                      for r, q in relays]
        send = SendStage(self.groups[0].label if self.groups else "tail", chans[0],
                         capacity=self.capacity, pools=pools, stop=head_stop)
        recv = RecvStage("tail", chans[-1], pools=pools, stop=tail_stop)
        head_stages = [PooledSource(self.head[0], pools[0], head_stop), *self.head[1:]]
        head = Pipeline([*head_stages, send], capacity=INNER_CAPACITY, stop=head_stop,
                        sinks=head_sinks + forwards + [f for r in relay_runs
                                                       for f in r.forwards[:1] if r.in_head])
        # with relayed sinks, the tail's last stage (the mosaic) is closed after they have
        # ended, as the thread runtime closes its stages after its sinks: a sink that fails
        # late still marks the mosaic failed
        relays_done = threading.Event()
        last: Stage = self.tail[-1]
        if relay_runs:
            last = AfterRelays(last, relays_done, abort.is_set)
        tail = Pipeline([recv, *self.tail[:-1], last], capacity=INNER_CAPACITY,
                        stop=tail_stop,
                        sinks=tail_sinks + [r.forwards[-1] for r in relay_runs if r.in_tail])
        for r in relay_runs:
            r.bind([head, tail])
        outcome: dict[str, Any] = {}

        def run_local(key: str, pipe: Pipeline) -> None:
            try:
                # frozen around both; OpenCV's threads set around the whole run
                outcome[key] = pipe.run(freeze_gc=False, limit_opencv=False)
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                outcome[key] = exc
                abort.set()

        threads = [threading.Thread(target=run_local, args=(k, p), name=f"local-{k}",
                                    daemon=True) for k, p in (("head", head), ("tail", tail))]
        relay_threads = [threading.Thread(target=run_local, args=(r.key, r.pipe),
                                          name=r.key, daemon=True) for r in relay_runs]
        for t in threads + relay_threads:
            t.start()
        remote = [StageStats(n) for w in workers[:len(self.groups)] for n in w.stages]

        def stop_all() -> None:
            abort.set()
            for p in [head, tail, *(r.pipe for r in relay_runs)]:
                p.cancel()
            relays_done.set()
            for t in threads + relay_threads:
                t.join()
            for r in relay_runs:
                r.q.cancel_join_thread()

        def end_relays() -> None:
            """Every chain has ended (the tail's last stage waits to be closed): the
            relayed sinks get the last statistics, then the end of stream."""
            reports = _reports(workers)
            final = live_stages(self, head.stats, tail.stats, reports)
            for r in relay_runs:
                r.finish(time.perf_counter() - t_start, final, chain_queues(
                    self, [q.stats for q in head.queues], [q.stats for q in tail.queues],
                    send.stats, reports), reports)
            for t in relay_threads:
                t.join()
            relays_done.set()

        try:
            while any(t.is_alive() for t in threads) or not all(
                    w.report is not None for w in workers):
                reported = all(w.report is not None for w in workers)
                if relay_runs and reported and not threads[0].is_alive():
                    # only the tail is left: its end, then the relays'
                    assert isinstance(last, AfterRelays)
                    if relays_done.is_set():  # the tail is closing
                        threads[1].join(self.progress_s)
                    elif last.ended.wait(self.progress_s):
                        end_relays()
                        continue
                elif reported:
                    # every worker has reported: what is left is a local chain's end, so
                    # wait on it, not on the results queue (which nothing more reaches: a
                    # poll would hold the end, and the wall time, up to progress_s longer)
                    next(t for t in threads if t.is_alive()).join(self.progress_s)
                else:
                    self._poll(workers, results, timeout=self.progress_s)
                if abort.is_set() or any(
                        (w.report is None and not w.proc.is_alive())
                        or (w.report is not None and w.report["kind"] == "error")
                        for w in workers):
                    stop_all()
                    self._poll(workers, results, timeout=0.5, drain=True)
                    break
                if remote:
                    remote[-1].frames = recv.done
                elapsed = time.perf_counter() - t_start
                if self.on_progress is not None:
                    self.on_progress(head.stats[:-1] + remote + tail.stats[1:], elapsed)
                # a worker's figures come with its report: not in the live statistics
                live = head.stats[:-1] + tail.stats[1:]
                for r in relay_runs:
                    if not relays_done.is_set():
                        r.snapshot(elapsed, live, chain_queues(
                            self, [q.stats for q in head.queues],
                            [q.stats for q in tail.queues], send.stats, _reports(workers)),
                            _reports(workers))
            if relay_runs and not relays_done.is_set():  # the tail failed: nothing waits
                stop_all()
        except BaseException:  # Ctrl-C or the progress display: stop everything cleanly
            stop_all()
            raise
        for t in threads + relay_threads:
            t.join()
        self._raise_failure(workers, outcome, [r.key for r in relay_runs])
        return process_result(self, outcome, send.stats, forwards, [w.label for w in workers],
                              _reports(workers), relay_runs, t_start)

    def _raise_failure(self, workers: list[_Worker], outcome: dict[str, Any],
                       relay_keys: list[str]) -> None:
        for key in ("head", "tail", *relay_keys):
            exc = outcome.get(key)
            if isinstance(exc, StageFailed):
                raise exc
        for w in workers:
            if w.report is not None and w.report["kind"] == "error":
                raise StageFailed(w.report["stage"], rebuild_exception(w.report))
        for w in workers:
            if w.report is None or w.report["kind"] != "done":
                code = w.proc.exitcode
                raise StageFailed(w.stages[0], RuntimeError(
                    f"worker process '{w.label}' ended without finishing (exit code {code})"))
        for key in ("head", "tail", *relay_keys):
            exc = outcome.get(key)
            if isinstance(exc, BaseException):
                raise exc
