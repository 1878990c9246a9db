"""Worker processes of the process runtime: what they run and how they report.

A worker (:func:`worker_main`, started with the ``spawn`` context) builds its stages itself
by a module-level factory function and JSON arguments (:class:`WorkerGroup`, or a
:class:`HostedSink`; the function travels by its qualified name), so no stage and no pixel
is pickled; it runs them with the thread
runtime between a :class:`~sffscan.pipeline.channels.RecvStage` and a
:class:`~sffscan.pipeline.channels.SendStage`, and reports ``ready``, then ``done`` (with
its statistics), ``error`` (stage, exception type, message, traceback) or ``cancelled``
as JSON on the results queue. It stops when the main process writes to its control pipe,
and dies with the main process (:mod:`sffscan.pipeline.spawn`).
"""

from __future__ import annotations

import importlib
import json
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sffscan.pipeline.channels import RecvStage, SendStage, is_channel_stage, own_queues, own_stages
from sffscan.pipeline.heap import keep_freed_memory
from sffscan.pipeline.relays import Relay, relay_forwarder, relay_report
from sffscan.pipeline.runtime import Pipeline, PipelineCancelled, StageFailed
from sffscan.pipeline.shm_ring import PoolSpec, SlotPool
from sffscan.pipeline.spawn import helper_start, watch_stop
from sffscan.stages.bands import BAND_CPU_KEY
from sffscan.stages.protocol import FullPolicy, Sink, Stage

#: capacity of the queues between the stages inside one process (the channels between
#: processes have the pipeline's ``capacity``)
INNER_CAPACITY = 2


@dataclass(frozen=True)
class WorkerGroup:
    """Stages run together in one worker process, built there by ``factory(**kwargs)``.

    ``factory`` is a module-level function (a spawned process imports it by name)
    returning the list of stages; ``kwargs`` must be JSON-able. ``stages`` names what the
    factory builds, in order (for the statistics). ``spawns``: its stages start processes
    of their own (band processes), so the worker is not a daemonic process (which may not
    have children); it dies with the main process all the same
    (:func:`sffscan.pipeline.spawn.helper_start`).
    """

    label: str
    factory: Callable[..., list[Stage]]
    kwargs: dict[str, Any]
    stages: tuple[str, ...]
    spawns: bool = False


@dataclass(frozen=True)
class HostedSink:
    """A sink run in its own process, fed through a shared-memory channel, built there by
    ``factory(**kwargs)`` (as a :class:`WorkerGroup`'s stages)."""

    name: str
    taps: tuple[str, ...]
    capacity: int
    policy: FullPolicy
    factory: Callable[..., Sink]
    kwargs: dict[str, Any]


class RemoteError(RuntimeError):
    """The cause of a failure in a worker, when its exception type cannot be rebuilt."""

    def __init__(self, type_name: str, message: str, remote_traceback: str) -> None:
        super().__init__(message)
        self.type_name = type_name
        self.remote_traceback = remote_traceback


def rebuild_exception(info: dict[str, Any]) -> BaseException:
    """The worker's exception: the same type when it takes one message, else RemoteError."""
    try:
        mod = importlib.import_module(info["module"])
        cls = getattr(mod, info["type"])
        if isinstance(cls, type) and issubclass(cls, Exception):
            exc = cls(info["message"])
            if str(exc) == info["message"]:
                return exc
    except Exception:  # noqa: BLE001, S110 - any type that cannot be rebuilt is wrapped
        pass
    err = RemoteError(info["type"], info["message"], info.get("traceback", ""))
    return err


def worker_main(group: dict[str, Any], kind: str, pool_specs: list[dict[str, Any]],
                syncs: list[tuple[Any, Any]], in_q: Any, out_q: Any, results: Any,
                control: Any, parent: int, producers: int = 1,
                relays: list[tuple[Relay, Any]] | None = None) -> None:
    """Entry point of a worker process (``spawn``): build, report ready, run, report.

    ``in_q`` None: the group's first stage is a source (the simulator's render workers);
    else the chain starts with the items of that channel. ``control`` is the read end of a
    pipe from the main process: a message there stops the worker (another part failed, or
    the consumer closed); end of file means the main process is gone. ``relays``: (relay,
    its channel) for each sink of the main process that taps some of this worker's
    stages; their forwarders' statistics come back in the report. ``group["opencv_threads"]``
    (optional): OpenCV's threads in this process (:mod:`sffscan.pipeline.opencv_threads`);
    ``group["one_thread"]`` (optional): the chain in one thread (``Pipeline``'s
    ``one_thread``).
    """
    helper_start(parent)
    keep_freed_memory()
    if group.get("opencv_threads") is not None:  # this process is the scan's: no restore
        import cv2

        cv2.setNumThreads(int(group["opencv_threads"]))
    label = group["label"]
    pools = [SlotPool(PoolSpec.from_json(s), sync, create=False)
             for s, sync in zip(pool_specs, syncs, strict=True)]
    stop, done, aborted = threading.Event(), threading.Event(), threading.Event()
    pipe: Pipeline | None = None

    def report(msg: dict[str, Any]) -> None:
        results.put(json.dumps({"label": label, **msg}))

    def on_stop() -> None:
        aborted.set()
        stop.set()
        if pipe is not None:
            pipe.cancel()

    watch_stop(control, parent, on_stop, done)
    try:
        try:
            built = group["factory"](**group["kwargs"])
            stages: list[Stage] = [built] if kind == "sink" else list(built)
            recv = None if in_q is None else RecvStage(label, in_q, pools=pools, stop=stop,
                                                       producers=producers)
            chain: list[Stage] = [*([recv] if recv is not None else []), *stages]
            if out_q is not None:
                chain.append(SendStage(label, out_q, capacity=group["capacity"], pools=pools,
                                       stop=stop, count_of=recv))
            forwards = []
            for relay, rq in relays or ():
                mine = tuple(t for t in relay.taps if t in {s.name for s in stages})
                forwards.append(relay_forwarder(relay, mine, rq, pools=pools, stop=stop))
            built_pipe = Pipeline(chain, capacity=INNER_CAPACITY, stop=stop,
                                  sinks=list(forwards),
                                  one_thread=bool(group.get("one_thread", False)))
            built_pipe.prepare()  # before "ready": the main process's clock starts there
        except StageFailed as err:
            report({"kind": "error", "stage": err.stage, **_exc_info(err.cause)})
            return
        except BaseException as exc:  # noqa: BLE001 - reported as the group's failure
            report({"kind": "error", "stage": label, **_exc_info(exc)})
            return
        pipe = built_pipe
        if aborted.is_set():  # stopped while it was being built
            report({"kind": "cancelled"})
            return
        report({"kind": "ready"})
        cpu0 = time.process_time()
        try:
            result = pipe.run(limit_opencv=False)  # OpenCV's threads: set above
        except StageFailed as err:
            aborted.set()
            report({"kind": "error", "stage": err.stage, **_exc_info(err.cause)})
        except PipelineCancelled:
            report({"kind": "cancelled"})
        else:
            send = chain[-1]
            fw = {f.name for f in forwards}
            # the band processes this worker started (their streaming CPU, BAND_CPU_KEY)
            helpers = sum(float(v.get(BAND_CPU_KEY, 0.0)) for v in result.extras.values()
                          if isinstance(v, dict))
            report({"kind": "done", "cpu_s": time.process_time() - cpu0 + helpers,
                    "channel": send.stats.to_json() if isinstance(send, SendStage) else None,
                    "stages": [st.to_json() for st in own_stages(result.stages, fw)],
                    "queues": [q.to_json() for q in own_queues(result.queues, fw)],
                    "extras": {k: v for k, v in result.extras.items()
                               if not is_channel_stage(k) and k not in fw},
                    "relays": {f.name: relay_report(f, result) for f in forwards}})
    finally:
        done.set()
        if aborted.is_set():  # nobody will read what is left
            for q in [out_q, *(rq for _, rq in relays or ())]:
                if q is not None:
                    q.cancel_join_thread()
        for p in pools:
            p.close()


def _exc_info(exc: BaseException) -> dict[str, Any]:
    return {"type": type(exc).__name__, "module": type(exc).__module__, "message": str(exc),
            "traceback": "".join(traceback.format_exception(exc))[-4000:]}


