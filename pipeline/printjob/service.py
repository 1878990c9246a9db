"""The print-job service: layer events in, scan and analysis, a verdict per layer out.

A printer link (:mod:`printer_links`: the OctoPrint plug-in, the Moonraker agent, the
DAQ's start/stop lines) tells the service that a layer is printed; the service runs the
layer's scan through a :class:`LayerHandler`, then its analysis, and answers.

Timing rule: only the scan holds the print. :meth:`JobService.layer` returns when the scan
is done (``verdict = "pending"``); the analysis runs in one bounded background worker and
its verdict is read later (:meth:`JobService.record`, or the ``alerts`` of the next
reply). A *strict* job waits for the verdict too. Every wait has a timeout: a scan that
does not end within ``scan_timeout_s``, or a strict verdict not ready within
``verdict_timeout_s``, releases the hold and records the layer ``unknown`` with the
reason. A layer is never ``pass`` without an analysis that said so.

The models and the state file are in :mod:`.links_models` (re-exported here).

State: each job is a folder ``STORE/JOB_ID`` holding the handler's outputs and
``service_state.json`` (:class:`JobState`, written atomically after every change). After a
restart, starting the same job id resumes it: finished layers are not scanned again, a
scan cut by the restart is recorded ``unknown``, an analysis cut by it is run again.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sffscan.pipeline.printjob.links_models import (
    STATE_FILE,
    Analysis,
    JobEnd,
    JobStart,
    JobState,
    JobStatus,
    LayerEvent,
    LayerHandler,
    LayerRecord,
    LayerReply,
    ObjectOutline,
    ScanResult,
    ScanState,
    ServiceError,
    Verdict,
    read_state,
    write_state,
)

log = logging.getLogger(__name__)

__all__ = ["STATE_FILE", "Analysis", "JobEnd", "JobService", "JobStart", "JobState",
           "JobStatus", "LayerEvent", "LayerHandler", "LayerRecord", "LayerReply",
           "ObjectOutline", "ScanResult", "ScanState", "ServiceError", "Verdict",
           "read_state", "write_state"]


@dataclass
class _Work:
    job: JobStart
    event: LayerEvent
    folder: Path
    done: threading.Event = field(default_factory=threading.Event)
    scan: ScanResult | None = None
    error: str | None = None
    seconds: float = 0.0


_STOP = object()


class JobService:
    """One printer's jobs: the scan worker, the analysis worker and the job states.

    Parameters
    ----------
    store : path-like
        Folder of the job folders.
    handler : LayerHandler
        What scans and analyses a layer.
    strict : bool, keyword-only
        Default of :attr:`JobStart.strict`: wait for each verdict before answering.
    scan_timeout_s, verdict_timeout_s : float, keyword-only
        Longest hold for a scan, and for a strict verdict after it, s.
    analysis_queue : int, keyword-only
        Layers that may wait for the analysis worker; one more is recorded ``unknown``.
    on_verdict : callable, keyword-only
        ``(job_id, record)`` called by the analysis worker with each verdict (a printer link
        that acts on it: a status line, a pause); exceptions are logged, not raised.
    """

    def __init__(self, store: str | Path, handler: LayerHandler, *, strict: bool = False,
                 scan_timeout_s: float = 120.0, verdict_timeout_s: float = 30.0,
                 analysis_queue: int = 4,
                 on_verdict: Callable[[str, LayerRecord], None] | None = None) -> None:
        if scan_timeout_s <= 0 or verdict_timeout_s <= 0 or analysis_queue < 1:
            raise ValueError("scan_timeout_s and verdict_timeout_s must be > 0 and "
                             "analysis_queue >= 1")
        self.store = Path(store)
        self.store.mkdir(parents=True, exist_ok=True)
        self.handler = handler
        self.strict = strict
        self.scan_timeout_s = scan_timeout_s
        self.verdict_timeout_s = verdict_timeout_s
        self.on_verdict = on_verdict
        self._lock = threading.RLock()  # guards _jobs and every JobState
        self._jobs: dict[str, JobState] = {}
        self._verdict_ready: dict[tuple[str, int], threading.Event] = {}
        self._scan_q: queue.Queue[Any] = queue.Queue(maxsize=1)
        self._analysis_q: queue.Queue[Any] = queue.Queue(maxsize=analysis_queue)
        self._busy: _Work | None = None  # the scan in progress (also after its timeout)
        self._closed = False
        self._threads = [threading.Thread(target=self._scan_loop, name="sffscan-scan",
                                          daemon=True),
                         threading.Thread(target=self._analysis_loop, name="sffscan-analysis",
                                          daemon=True)]
        for t in self._threads:
            t.start()

    # --- requests -----------------------------------------------------------------------

    def start_job(self, start: JobStart) -> JobStatus:
        with self._lock:
            self._check_open()
            folder = self.store / start.job_id
            path = folder / STATE_FILE
            other = [j for j, s in self._jobs.items() if s.status == "open" and j != start.job_id]
            if other:
                raise ServiceError(409, f"job {other[0]!r} is still open: end it first")
            resumed = path.exists()
            if resumed:
                state = read_state(path)
                if state.status == "ended":
                    raise ServiceError(409, f"job {start.job_id!r} has ended ({state.end}); "
                                            "start a new job id")
                if start.strict is not None:
                    state.job = state.job.model_copy(update={"strict": start.strict})
                self._jobs[start.job_id] = state
                self._resume(state, folder)
            else:
                folder.mkdir(parents=True, exist_ok=True)
                state = JobState(job=start)
                self._jobs[start.job_id] = state
            write_state(path, state)
            log.info("job %s %s", start.job_id, "resumed" if resumed else "started")
            return self._status(state, resumed=resumed)

    def layer(self, job_id: str, event: LayerEvent) -> LayerReply:
        """Scan layer ``event.layer``; returns after the scan (strict: after the verdict),
        or after a timeout with the layer ``unknown``."""
        with self._lock:
            state = self._open_job(job_id)
            old = state.layers.get(event.layer)
            if old is not None and old.scan != "running":
                return self._reply(state, old, repeated=True)
            if old is not None:
                raise ServiceError(409, f"layer {event.layer}: its scan is still running")
            if state.layers and event.layer < max(state.layers):
                raise ServiceError(409, f"layer {event.layer} arrived after layer "
                                        f"{max(state.layers)}: layer events must come in order")
            folder = self.store / job_id
            busy = self._busy
            if busy is not None:
                rec = LayerRecord(layer=event.layer, z_mm=event.z_mm, scan="skipped",
                                  verdict="unknown",
                                  reason=f"scanner still busy with layer {busy.event.layer} "
                                         "(its scan timed out)")
                return self._reply(state, self._store(state, rec))
            work = _Work(state.job, event, folder)
            self._busy = work
            self._store(state, LayerRecord(layer=event.layer, z_mm=event.z_mm, scan="running",
                                           verdict="pending"))
        try:
            self._scan_q.put(work, timeout=self.scan_timeout_s)
        except queue.Full:  # pragma: no cover - _busy admits one scan at a time
            work.error, work.seconds = "scan queue full", 0.0
            work.done.set()
        finished = work.done.wait(self.scan_timeout_s)
        with self._lock:
            if not finished:
                rec = LayerRecord(layer=event.layer, z_mm=event.z_mm, scan="timeout",
                                  verdict="unknown",
                                  reason=f"scan not done within {self.scan_timeout_s:g} s: "
                                         "hold released")
                log.warning("job %s layer %d: %s", job_id, event.layer, rec.reason)
                return self._reply(state, self._store(state, rec))
            rec = self._after_scan(state, work)
            strict = self.strict if state.job.strict is None else state.job.strict
            ready = self._verdict_ready.get((job_id, event.layer))
        if strict and ready is not None and not ready.wait(self.verdict_timeout_s):
            with self._lock:
                cur = state.layers[event.layer]
                if cur.verdict == "pending":
                    rec = cur.model_copy(update={
                        "verdict": "unknown",
                        "reason": f"verdict not ready within {self.verdict_timeout_s:g} s "
                                  "(strict): hold released"})
                    log.warning("job %s layer %d: %s", job_id, event.layer, rec.reason)
                    self._store(state, rec)
        with self._lock:
            return self._reply(state, state.layers[event.layer])

    def record(self, job_id: str, layer: int) -> LayerRecord:
        with self._lock:
            state = self._job(job_id)
            if layer not in state.layers:
                raise ServiceError(404, f"job {job_id!r} has no layer {layer}")
            return state.layers[layer]

    def status(self, job_id: str) -> JobStatus:
        with self._lock:
            return self._status(self._job(job_id))

    def end_job(self, job_id: str, end: JobEnd, *, wait_s: float = 10.0) -> JobStatus:
        """End a job; waits up to ``wait_s`` for verdicts still pending (the rest stay
        pending in the state file, and run again if the job is resumed)."""
        with self._lock:
            state = self._open_job(job_id)
            waits = [e for (j, _), e in self._verdict_ready.items() if j == job_id]
        deadline = time.monotonic() + wait_s
        for ev in waits:
            ev.wait(max(0.0, deadline - time.monotonic()))
        with self._lock:
            state.status, state.end = "ended", end
            write_state(self.store / job_id / STATE_FILE, state)
            log.info("job %s ended: %s %s", job_id, end.outcome, end.reason)
            return self._status(state)

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the workers (a scan or analysis in progress is waited for, up to
        ``timeout_s`` each); the job states stay on disk for a resume."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for q in (self._scan_q, self._analysis_q):
            try:
                q.put(_STOP, timeout=timeout_s)
            except queue.Full:
                log.error("a worker queue stayed full for %g s at close", timeout_s)
        for t in self._threads:
            t.join(timeout_s)
            if t.is_alive():
                log.error("%s still running %g s after close (a handler that does not "
                          "return)", t.name, timeout_s)

    def __enter__(self) -> JobService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- internals (called with the lock held) ---------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise ServiceError(503, "the service is shutting down")

    def _job(self, job_id: str) -> JobState:
        state = self._jobs.get(job_id)
        if state is None:
            path = self.store / job_id / STATE_FILE
            if not path.exists():
                raise ServiceError(404, f"no job {job_id!r} (start it with POST /jobs)")
            state = read_state(path)
            if state.status == "open":
                raise ServiceError(409, f"job {job_id!r} was open when the service stopped: "
                                        "start it again (POST /jobs) to resume it")
        return state

    def _open_job(self, job_id: str) -> JobState:
        self._check_open()
        state = self._job(job_id)
        if state.status != "open":
            raise ServiceError(409, f"job {job_id!r} has ended")
        return state

    def _store(self, state: JobState, rec: LayerRecord) -> LayerRecord:
        state.layers[rec.layer] = rec
        write_state(self.store / state.job.job_id / STATE_FILE, state)
        return rec

    def _reply(self, state: JobState, rec: LayerRecord, *, repeated: bool = False) -> LayerReply:
        alerts = [r for _, r in sorted(state.layers.items()) if r.verdict in ("warn", "fail")]
        return LayerReply(job_id=state.job.job_id, record=rec, repeated=repeated, alerts=alerts)

    def _status(self, state: JobState, *, resumed: bool = False) -> JobStatus:
        counts: dict[str, int] = {}
        for r in state.layers.values():
            counts[r.verdict] = counts.get(r.verdict, 0) + 1
        strict = self.strict if state.job.strict is None else state.job.strict
        return JobStatus(job_id=state.job.job_id, status=state.status, resumed=resumed,
                         strict=strict,
                         layers_done=sorted(n for n, r in state.layers.items()
                                            if r.scan != "running"),
                         pending=sorted(n for n, r in state.layers.items()
                                        if r.verdict == "pending"),
                         counts=counts)

    def _after_scan(self, state: JobState, work: _Work) -> LayerRecord:
        ev = work.event
        if work.error is not None or work.scan is None:
            rec = LayerRecord(layer=ev.layer, z_mm=ev.z_mm, scan="failed", verdict="unknown",
                              reason=f"scan failed: {work.error}", scan_s=work.seconds)
            log.warning("job %s layer %d: %s", state.job.job_id, ev.layer, rec.reason)
            return self._store(state, rec)
        out = work.scan.output
        rel = None if out is None else os.path.relpath(out, work.folder)
        rec = LayerRecord(layer=ev.layer, z_mm=ev.z_mm, scan="done", verdict="pending",
                          scan_s=round(work.seconds, 3), output=rel)
        self._store(state, rec)
        self._queue_analysis(state, work)
        return state.layers[ev.layer]

    def _queue_analysis(self, state: JobState, work: _Work) -> None:
        key = (state.job.job_id, work.event.layer)
        ready = threading.Event()
        try:
            self._analysis_q.put_nowait((work, ready))
        except queue.Full:
            rec = state.layers[work.event.layer].model_copy(update={
                "verdict": "unknown",
                "reason": f"analysis queue full ({self._analysis_q.maxsize} layers waiting)"})
            self._store(state, rec)
            return
        self._verdict_ready[key] = ready

    def _resume(self, state: JobState, folder: Path) -> None:
        for n, rec in sorted(state.layers.items()):
            if rec.scan == "running":
                self._store(state, rec.model_copy(update={
                    "scan": "failed", "verdict": "unknown",
                    "reason": "the service stopped during this layer's scan"}))
            elif rec.verdict == "pending":
                event = LayerEvent(layer=n, z_mm=rec.z_mm)
                out = None if rec.output is None else folder / rec.output
                work = _Work(state.job, event, folder, scan=ScanResult(output=out))
                self._queue_analysis(state, work)

    # --- workers --------------------------------------------------------------------------

    def _scan_loop(self) -> None:
        while True:
            work = self._scan_q.get()
            if work is _STOP:
                return
            t0 = time.perf_counter()
            try:
                work.scan = self.handler.scan(work.job, work.event, work.folder)
            except Exception as err:  # recorded as the layer's reason, never raised here
                work.error = f"{type(err).__name__}: {err}"
            work.seconds = time.perf_counter() - t0
            with self._lock:
                self._busy = None
                if self._timed_out(work):
                    log.warning("job %s layer %d: scan ended %.1f s after its hold was "
                                "released; kept, verdict stays unknown",
                                work.job.job_id, work.event.layer, work.seconds)
            work.done.set()

    def _timed_out(self, work: _Work) -> bool:
        rec = self._jobs.get(work.job.job_id)
        layer = None if rec is None else rec.layers.get(work.event.layer)
        return layer is not None and layer.scan == "timeout"

    def _analysis_loop(self) -> None:
        while True:
            item = self._analysis_q.get()
            if item is _STOP:
                return
            work, ready = item
            t0 = time.perf_counter()
            try:
                assert work.scan is not None
                result = self.handler.analyse(work.job, work.event, work.scan, work.folder)
            except Exception as err:
                result = Analysis(verdict="unknown",
                                  reason=f"analysis failed: {type(err).__name__}: {err}")
            seconds = round(time.perf_counter() - t0, 3)
            stored = None
            with self._lock:
                state = self._jobs.get(work.job.job_id)
                cur = None if state is None else state.layers.get(work.event.layer)
                if state is not None and cur is not None:
                    late = cur.verdict == "unknown" and cur.scan == "done"
                    stored = self._store(state, cur.model_copy(update={
                        "verdict": result.verdict, "reason": result.reason,
                        "objects": dict(result.objects), "analysis_s": seconds,
                        "late": late}))
                    if result.verdict in ("warn", "fail"):
                        log.warning("job %s layer %d: %s: %s", work.job.job_id,
                                    work.event.layer, result.verdict, result.reason)
                self._verdict_ready.pop((work.job.job_id, work.event.layer), None)
            ready.set()
            if stored is not None and self.on_verdict is not None:
                try:
                    self.on_verdict(work.job.job_id, stored)
                except Exception:
                    log.exception("on_verdict failed for job %s layer %d", work.job.job_id,
                                  work.event.layer)
