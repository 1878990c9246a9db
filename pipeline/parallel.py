"""Process execution: groups of stages in worker processes, frames in shared memory.

    main process                 worker "registration"        worker "focus"             main
    source -> speed_shift -> ch1 -> registration -> ch2 -> focus_measure -> depth -> ch3 -> mosaic
           \\-> ForwardSink -> ch4 -> recorder (own process)
    viewer (main) <- ch5 <- forwarders where registration, focus_measure, depth run (relay)

Each worker runs its group of stages with the thread runtime (:class:`Pipeline`), between a
:class:`~sffscan.pipeline.channels.RecvStage` and a
:class:`~sffscan.pipeline.channels.SendStage`; the main process runs the head (the source)
and the tail (the mosaic writer, which owns the output) the same way. Workers are started
with the ``spawn`` context (no fork of a process with torch or OpenCV threads) and build
their stages themselves from a factory named ``"module:function"`` and JSON arguments (the
scan configuration): no stage and no pixel is pickled.

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
where the sink runs behind its own queue and policy, as in the thread runtime (a
:class:`~sffscan.pipeline.worker.Relay`; see :meth:`ProcessPipeline.run`). The main
process sends the sink the pipeline's statistics too (``wants_stats``), the last ones
after every worker has reported, then the end of stream.

Memory is bounded by the pools: ``sum(slots * slot_bytes)``, fixed at start (see
:func:`sffscan.pipeline.scan_processes.ring_plan` for the scan pipeline's formula).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sffscan.pipeline.channels import WAIT_S, ForwardSink, RecvStage, SendStage
from sffscan.pipeline.runtime import (
    Pipeline,
    PipelineResult,
    PipelineStopped,
    QueueStats,
    StageFailed,
    StageStats,
    StatsSnapshot,
    gc_frozen,
)
from sffscan.pipeline.shm_ring import PoolStopped, SlotPool, new_spec
from sffscan.pipeline.wire import encode
from sffscan.pipeline.worker import (
    INNER_CAPACITY,
    HostedSink,
    Relay,
    WorkerGroup,
    is_channel_stage,
    rebuild_exception,
    relay_forwarder,
    relay_of,
    worker_main,
)
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink, Stage

log = logging.getLogger(__name__)

#: longest wait for the workers to import and build their stages, s
START_TIMEOUT_S = 300.0
#: how long a worker gets to finish after the abort before it is terminated, s
JOIN_TIMEOUT_S = 10.0
def relayed_sinks(sinks: list[Sink], head: list[str], tail: list[str]) -> list[Sink]:
    """The main process's sinks that are relayed: those that tap stages other than the
    head's alone or the tail's alone (``head``, ``tail``: the stage names)."""
    return [k for k in sinks if not (set(k.taps) <= set(head) or set(k.taps) <= set(tail))]


class PooledSource(Stage):
    """The source stage, its frames copied once into the frame pool (then passed on by
    reference to every process and sink)."""

    def __init__(self, inner: Stage, pool: SlotPool, stop: threading.Event) -> None:
        self.inner = inner
        self.name = inner.name
        self.unit = inner.unit
        self.pool = pool
        self.stop = stop

    def produce(self) -> Iterator[Any]:
        for frame in self.inner.produce():
            img = frame.image
            if self.pool.locate(img) is None:
                try:
                    slot = self.pool.acquire(self.stop.is_set)
                except PoolStopped:
                    raise PipelineStopped(self.name) from None
                view = self.pool.array(slot, offset=0, shape=img.shape, dtype=img.dtype.str)
                np.copyto(view, img, casting="no")
                frame = Frame(frame.header, view)
            yield frame

    def close(self, *, failed: bool) -> None:
        self.inner.close(failed=failed)

    def extra_stats(self) -> dict[str, Any]:
        return self.inner.extra_stats()


class _Abort:
    """The main process's stop order to every worker: one pipe each (a worker polls its
    read end; end of file there means the main process died)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._writers: list[Any] = []
        self._readers: list[Any] = []

    def pipe(self, ctx: Any) -> Any:
        r, w = ctx.Pipe(duplex=False)
        self._readers.append(r)
        self._writers.append(w)
        return r

    def started(self) -> None:
        """The workers have their read ends: close ours."""
        for r in self._readers:
            r.close()
        self._readers.clear()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        if self.event.is_set():
            return
        self.event.set()
        for w in self._writers:
            with contextlib.suppress(OSError):
                w.send_bytes(b"stop")

    def close(self) -> None:
        self.started()
        for w in self._writers:
            w.close()
        self._writers.clear()


@dataclass
class _Worker:
    label: str
    proc: Any
    stages: tuple[str, ...]
    report: dict[str, Any] | None = None
    ready: bool = False


@dataclass
class ProcessPipeline:
    """head (main) -> groups (one worker process each) -> tail (main), plus sinks.

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
        docstring; :func:`~sffscan.pipeline.worker.relay_of`).
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

    def run(self) -> PipelineResult:
        ctx = mp.get_context("spawn")
        specs = [new_spec(label, slots=n, slot_bytes=b, kinds=k) for label, n, b, k in self.pools]
        syncs = [(ctx.Lock(), ctx.Semaphore(s.slots)) for s in specs]
        pools: list[SlotPool] = []
        workers: list[_Worker] = []
        abort = _Abort()
        results = ctx.Queue()
        stop = threading.Event()
        t_start = time.perf_counter()  # wall_s counts from the workers' readiness
        try:
            for s, sync in zip(specs, syncs, strict=True):
                pools.append(SlotPool(s, sync, create=True))
            chans = [ctx.Queue(self.capacity) for _ in range(len(self.groups) + 1)]
            sink_qs = [ctx.Queue(k.capacity) for k in self.hosted]
            relays = [relay_of(k) for k in self._relayed()]
            relay_qs = [ctx.Queue(r.capacity) for r in relays]
            pj = [s.to_json() for s in specs]
            for i, g in enumerate(self.groups):
                spec = {"label": g.label, "factory": g.factory, "kwargs": g.kwargs,
                        "capacity": self.capacity}
                mine = [(r.to_json(), q) for r, q in zip(relays, relay_qs, strict=True)
                        if set(r.taps) & set(g.stages)]
                p = ctx.Process(target=worker_main, name=f"sffscan-{g.label}",
                                args=(spec, "stages", pj, syncs, chans[i], chans[i + 1],
                                      results, abort.pipe(ctx), os.getpid(), 1, mine),
                                daemon=True)
                workers.append(_Worker(g.label, p, g.stages))
            for k, q in zip(self.hosted, sink_qs, strict=True):
                spec = {"label": k.name, "factory": k.factory, "kwargs": k.kwargs}
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
            self._join(workers)
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

    @staticmethod
    def _join(workers: list[_Worker]) -> None:
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        for w in workers:
            if w.proc.pid is None:
                continue
            w.proc.join(max(0.1, deadline - time.monotonic()))
            if w.proc.is_alive():
                log.warning("worker %s did not stop within %g s: terminated", w.label,
                            JOIN_TIMEOUT_S)
                w.proc.terminate()
                w.proc.join(5.0)
                if w.proc.is_alive():
                    w.proc.kill()
                    w.proc.join()

    # -- run -----------------------------------------------------------------------------
    def _relayed(self) -> list[Sink]:
        return relayed_sinks(self.sinks, [s.name for s in self.head],
                             [s.name for s in self.tail])

    def _run(self, pools: list[SlotPool], workers: list[_Worker], chans: list[Any],
             sink_qs: list[Any], results: Any, abort: _Abort, stop: threading.Event,
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
        forwards: list[Sink] = [
            ForwardSink(k.name, k.taps, q, capacity=k.capacity, policy=k.policy, pools=pools,
                        stop=head_stop) for k, q in zip(self.hosted, sink_qs, strict=True)]
        relayed = {r.name for r, _ in relays}
        head_sinks = [k for k in self.sinks if set(k.taps) <= head_names
                      and k.name not in relayed]
        tail_sinks = [k for k in self.sinks if k not in head_sinks and k.name not in relayed]
        relay_runs = [_RelayRun(r, q, next(k for k in self.sinks if k.name == r.name), pools,
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
            last = _AfterRelays(last, relays_done, abort.is_set)
        tail = Pipeline([recv, *self.tail[:-1], last], capacity=INNER_CAPACITY,
                        stop=tail_stop,
                        sinks=tail_sinks + [r.forwards[-1] for r in relay_runs if r.in_tail])
        for r in relay_runs:
            r.bind([head, tail])
        outcome: dict[str, Any] = {}

        def run_local(key: str, pipe: Pipeline) -> None:
            try:
                outcome[key] = pipe.run(freeze_gc=False)  # frozen around both
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
            final = [*head.stats[:-1],
                     *(StageStats(**s) for w in workers[:len(self.groups)]
                       for s in (w.report or {}).get("stages", [])), *tail.stats[1:]]
            for r in relay_runs:
                r.finish(time.perf_counter() - t_start, final, self._chain_queues(
                    [q.stats for q in head.queues], [q.stats for q in tail.queues],
                    send.stats, workers), workers)
            for t in relay_threads:
                t.join()
            relays_done.set()

        try:
            while any(t.is_alive() for t in threads) or not all(
                    w.report is not None for w in workers):
                reported = all(w.report is not None for w in workers)
                if relay_runs and reported and not threads[0].is_alive():
                    # only the tail is left: its end, then the relays'
                    assert isinstance(last, _AfterRelays)
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
                        r.snapshot(elapsed, live, self._chain_queues(
                            [q.stats for q in head.queues], [q.stats for q in tail.queues],
                            send.stats, workers), workers)
            if relay_runs and not relays_done.is_set():  # the tail failed: nothing waits
                stop_all()
        except BaseException:  # Ctrl-C or the progress display: stop everything cleanly
            stop_all()
            raise
        for t in threads + relay_threads:
            t.join()
        self._raise_failure(workers, outcome, [r.key for r in relay_runs])
        return self._result(head, tail, send, forwards, workers, outcome, t_start, relay_runs)

    def _chain_queues(self, head_q: list[QueueStats], tail_q: list[QueueStats],
                      send: QueueStats, workers: list[_Worker]) -> list[QueueStats]:
        """The queues of the main chain, in order, named as in the thread runtime: the
        head's, each channel (``stage->next stage``) and worker's, the tail's (a worker
        that has not reported yet shows zeros)."""
        sinks = {k.name for k in self.sinks} | {k.name for k in self.hosted}

        def own(qs: list[QueueStats]) -> list[QueueStats]:
            return [q for q in qs if not is_channel_stage(q.name)
                    and q.name.rsplit("->", 1)[-1] not in sinks]

        queues = own(head_q)
        channel, prev = send, self.head[-1].name
        for w, g in zip(workers, self.groups, strict=False):
            rep = w.report or {}
            queues.append(dataclasses.replace(channel, name=f"{prev}->{g.stages[0]}"))
            if rep.get("queues") is not None:
                queues += [QueueStats(**q) for q in rep["queues"]]
            else:
                queues += [QueueStats(f"{a}->{b}", INNER_CAPACITY, "block")
                           for a, b in zip(g.stages[:-1], g.stages[1:], strict=True)]
            channel = QueueStats(**rep["channel"]) if rep.get("channel") else QueueStats(
                "", self.capacity, "block")
            prev = g.stages[-1]
        queues.append(dataclasses.replace(channel, name=f"{prev}->{self.tail[0].name}"))
        return queues + own(tail_q)

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

    def _result(self, head: Pipeline, tail: Pipeline, send: SendStage,
                forwards: list[Sink], workers: list[_Worker], outcome: dict[str, Any],
                t_start: float, relay_runs: list[_RelayRun]) -> PipelineResult:
        rh: PipelineResult = outcome["head"]
        rt: PipelineResult = outcome["tail"]
        hosted = {k.name for k in self.hosted}
        relayed = {r.relay.name for r in relay_runs}
        sink_names = tuple(k.name for k in self.sinks) + tuple(hosted)
        stages = [s for s in rh.stages
                  if not is_channel_stage(s.name) and s.name not in sink_names]
        extras = {k: v for k, v in rh.extras.items() if not is_channel_stage(k)}
        for w in workers[:len(self.groups)]:
            rep = w.report or {}
            stages += [StageStats(**s) for s in rep.get("stages", [])]
            extras.update(rep.get("extras", {}))
        stages += [s for s in rt.stages
                   if not is_channel_stage(s.name) and s.name not in sink_names]
        queues = self._chain_queues(rh.queues, rt.queues, send.stats, workers)
        extras.update({k: v for k, v in rt.extras.items() if not is_channel_stage(k)})
        local = hosted | relayed  # sinks whose figures come from elsewhere
        sink_stages = [s for s in rh.stages + rt.stages
                       if s.name in sink_names and s.name not in local]
        sink_queues = [q for q in rh.queues + rt.queues
                       if q.name.rsplit("->", 1)[-1] in sink_names and not any(
                           q.name.endswith("->" + h) for h in local)]
        for k in forwards:
            assert isinstance(k, ForwardSink)
            rep = next((w.report or {} for w in workers if w.label == k.name), {})
            sink_stages += [StageStats(**s) for s in rep.get("stages", [])]
            sink_queues.append(k.stats)
            waited = rh.extras.get(k.name, {}).get("pipeline_waited_s", 0.0)
            extras[k.name] = {**rep.get("extras", {}).get(k.name, {}),
                              "pipeline_waited_s": waited}
        for r in relay_runs:
            rr: PipelineResult = outcome[r.key]
            sink_stages.append(rr.stages[-1])
            sink_queues.append(r.queue_stats(workers))
            extras[r.relay.name] = {**rr.extras.get(r.relay.name, {}),
                                    "pipeline_waited_s": round(r.waited_s(
                                        workers, rh, rt), 3)}
        return PipelineResult(wall_s=time.perf_counter() - t_start,
                              stages=stages + sink_stages, queues=queues + sink_queues,
                              extras=extras, sinks=sink_names)


class _AfterRelays(Stage):
    """The tail's last stage, closed only once the relayed sinks have ended (``done``);
    ``ended`` is set when it has finished its stream. Closed as failed if anything failed
    meanwhile (``failed_elsewhere``); a failing tail closes at once."""

    def __init__(self, inner: Stage, done: threading.Event,
                 failed_elsewhere: Callable[[], bool]) -> None:
        self.inner, self.done, self.failed_elsewhere = inner, done, failed_elsewhere
        self.name, self.unit = inner.name, inner.unit
        self.ended = threading.Event()

    def process(self, item: Any) -> Any:
        return self.inner.process(item)

    def finish(self) -> list[Any]:
        out = list(self.inner.finish())
        self.ended.set()
        return out

    def close(self, *, failed: bool) -> None:
        # ``done`` is set by the main thread whatever happens (end_relays, stop_all)
        while not failed and not self.done.wait(WAIT_S) and not self.failed_elsewhere():
            continue
        self.inner.close(failed=failed or self.failed_elsewhere())

    def extra_stats(self) -> dict[str, Any]:
        return self.inner.extra_stats()


class _RelayRun:
    """A relayed sink in the main process: its forwarders in the head and tail, and the
    chain ``recv -> sink`` (the sink behind a queue of the relay's capacity and the sink's
    own policy) that the workers' forwarders, these and the main process feed.

    The producers of the channel are the workers that run some of the taps, the head and
    tail forwarders, and the main process itself, which sends the end of stream once every
    chain has ended (after the last statistics): so the sink ends after everything it taps.
    """

    def __init__(self, relay: Relay, q: Any, sink: Sink, pools: list[SlotPool],
                 head_names: set[str], tail_names: set[str], head_stop: threading.Event,
                 tail_stop: threading.Event, remote_producers: int) -> None:
        self.relay, self.q, self.sink, self.pools = relay, q, sink, pools
        self.key = f"relay-{relay.name}"
        head_taps = tuple(t for t in relay.taps if t in head_names)
        tail_taps = tuple(t for t in relay.taps if t in tail_names)
        self.in_head, self.in_tail = bool(head_taps), bool(tail_taps)
        self.forwards: list[ForwardSink] = []
        if head_taps:
            self.forwards.append(relay_forwarder(relay, head_taps, q, pools=pools,
                                                 stop=head_stop))
        if tail_taps:
            self.forwards.append(relay_forwarder(relay, tail_taps, q, pools=pools,
                                                 stop=tail_stop))
        self.stop = threading.Event()
        self.local_queues: list[QueueStats] = []
        self.recv = RecvStage(relay.name, q, pools=pools, stop=self.stop,
                              producers=remote_producers + len(self.forwards) + 1)
        self.pipe = Pipeline([self.recv, sink], capacity=relay.capacity,
                             policies={sink.name: relay.policy}, stop=self.stop)

    @property
    def _inbox(self) -> Any:
        return self.pipe.queues[0]

    def queue_stats(self, workers: list[_Worker]) -> QueueStats:
        """The sink's queue as the summary shows it: the queue in front of the sink, with
        the drops of every forwarder and channel on the way added."""
        own = self._inbox.stats
        dropped = own.dropped + sum(f.stats.dropped for f in self.forwards) + sum(
            q.dropped for q in self.local_queues)
        for w in workers:
            rep = ((w.report or {}).get("relays") or {}).get(self.relay.name)
            if rep:
                dropped += rep["queue"]["dropped"] + rep["channel"]["dropped"]
        return QueueStats(f"{'+'.join(self.relay.taps)}->{self.relay.name}", own.capacity,
                          self.relay.policy.value, own.puts, dropped, own.max_fill,
                          own.fill_sum)

    def bind(self, pipes: list[Pipeline]) -> None:
        """Take the queues of ``pipes`` (head, tail) that feed this relay's forwarders."""
        self.local_queues = [q.stats for p in pipes for q in p.sink_queues
                             if q.name.rsplit("->", 1)[-1] == self.relay.name]

    def snapshot(self, elapsed: float, stages: list[StageStats], queues: list[QueueStats],
                 workers: list[_Worker]) -> QueueStats | None:
        """The pipeline's statistics to a sink that wants them (not to a blocking one);
        returns the sink's own queue figures in them."""
        if not self.sink.wants_stats or self.relay.policy is FullPolicy.BLOCK:
            return None
        # the main process is one of the channel's producers and sends its end of stream
        # after the last statistics (finish): none can come after the end of stream
        mine = self.queue_stats(workers)
        snap = StatsSnapshot(elapsed, tuple(copy.copy(s) for s in stages),
                             tuple([*(copy.copy(q) for q in queues), mine]))
        self._inbox.put(snap)
        return mine

    def finish(self, elapsed: float, stages: list[StageStats], queues: list[QueueStats],
               workers: list[_Worker]) -> None:
        """The last statistics, then the main process's end of stream."""
        mine = self.snapshot(elapsed, stages, queues, workers)
        if mine is not None:
            # putting them into a full queue dropped its oldest item: count that one too
            # (the sink reads these figures only after the items ahead of them, and a
            # queue is full only when there are many)
            mine.dropped = self.queue_stats(workers).dropped
        data = encode(END_OF_STREAM, self.pools, lambda: True)
        while True:
            try:
                self.q.put(data, timeout=WAIT_S)
                return
            except queue.Full:
                if self.stop.is_set():
                    return

    def waited_s(self, workers: list[_Worker], rh: PipelineResult,
                 rt: PipelineResult) -> float:
        """Time the chains waited for this sink (a blocking one falling behind)."""
        name = self.relay.name
        local = sum(r.extras.get(name, {}).get("pipeline_waited_s", 0.0) for r in (rh, rt))
        return local + sum(((w.report or {}).get("relays") or {}).get(name, {}).get(
            "pipeline_waited_s", 0.0) for w in workers)
