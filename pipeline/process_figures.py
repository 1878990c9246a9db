"""The figures of a run in processes, put together as the thread runtime shows them.

Each process runs its part of the chain with the thread runtime; a worker sends its own
stages' and queues' figures in its report (:func:`~sffscan.pipeline.worker.worker_main`),
the main process has the head's and the tail's. :func:`chain_queues` and
:func:`process_result` give one :class:`~sffscan.pipeline.stats.PipelineResult` in the
chain's order, with the names of the thread runtime: the channels between processes are
the queues ``stage->next stage``, the channel stages (``recv:``, ``send:``) are left out,
and a sink's figures come from where it ran (its own process, or the main process's
relay), with the drops of every forwarder and channel on its way.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Protocol

from sffscan.pipeline.channels import ForwardSink, is_channel_stage, own_queues, own_stages
from sffscan.pipeline.relays import RelayRun
from sffscan.pipeline.stats import PipelineResult, QueueStats, StageStats
from sffscan.pipeline.worker import INNER_CAPACITY, HostedSink, WorkerGroup
from sffscan.stages.protocol import Sink, Stage


class ProcessLayout(Protocol):
    """The layout of a run in processes
    (:class:`sffscan.pipeline.parallel.ProcessPipeline`)."""

    head: list[Stage]
    groups: list[WorkerGroup]
    tail: list[Stage]
    capacity: int
    sinks: list[Sink]
    hosted: list[HostedSink]


def sink_names(pipe: ProcessLayout) -> tuple[str, ...]:
    """Every sink of ``pipe``: those of the main process, then the hosted ones."""
    return tuple(k.name for k in pipe.sinks) + tuple(k.name for k in pipe.hosted)


def chain_queues(pipe: ProcessLayout, head_q: list[QueueStats], tail_q: list[QueueStats],
                 send: QueueStats, reports: list[dict[str, Any]]) -> list[QueueStats]:
    """The queues of the main chain, in order, named as in the thread runtime: the
    head's, each channel (``stage->next stage``) and worker's, the tail's (a worker
    that has not reported yet, an empty report, shows zeros). ``reports``: the workers',
    the groups' first, in order."""
    sinks = sink_names(pipe)
    queues = own_queues(head_q, sinks)
    channel, prev = send, pipe.head[-1].name
    for rep, g in zip(reports, pipe.groups, strict=False):
        queues.append(dataclasses.replace(channel, name=f"{prev}->{g.stages[0]}"))
        if rep.get("queues") is not None:
            queues += [QueueStats(**q) for q in rep["queues"]]
        else:
            queues += [QueueStats(f"{a}->{b}", INNER_CAPACITY, "block")
                       for a, b in zip(g.stages[:-1], g.stages[1:], strict=True)]
        channel = QueueStats(**rep["channel"]) if rep.get("channel") else QueueStats(
            "", pipe.capacity, "block")
        prev = g.stages[-1]
    queues.append(dataclasses.replace(channel, name=f"{prev}->{pipe.tail[0].name}"))
    return queues + own_queues(tail_q, sinks)


def live_stages(pipe: ProcessLayout, head: list[StageStats], tail: list[StageStats],
                reports: list[dict[str, Any]]) -> list[StageStats]:
    """The main chain's stages, in order: the head's (without its channel), the workers'
    from their reports (none from a worker not in yet), the tail's (without its own)."""
    remote = [StageStats(**s) for rep in reports[:len(pipe.groups)]
              for s in rep.get("stages", [])]
    return [*head[:-1], *remote, *tail[1:]]


def process_result(pipe: ProcessLayout, outcome: dict[str, Any], send: QueueStats,
                   forwards: list[ForwardSink], labels: list[str],
                   reports: list[dict[str, Any]], relay_runs: list[RelayRun],
                   t_start: float) -> PipelineResult:
    """The whole run's figures: ``outcome`` holds the head's and tail's results (keys
    ``head``, ``tail``) and each relay's (its ``key``); ``forwards`` feed the hosted
    sinks; ``labels`` and ``reports``: the workers' (groups first, then hosted sinks)."""
    rh: PipelineResult = outcome["head"]
    rt: PipelineResult = outcome["tail"]
    hosted = {k.name for k in pipe.hosted}
    relayed = {r.relay.name for r in relay_runs}
    sinks = sink_names(pipe)
    stages = own_stages(rh.stages, sinks)
    extras = {k: v for k, v in rh.extras.items() if not is_channel_stage(k)}
    for rep in reports[:len(pipe.groups)]:
        stages += [StageStats(**s) for s in rep.get("stages", [])]
        extras.update(rep.get("extras", {}))
    stages += own_stages(rt.stages, sinks)
    queues = chain_queues(pipe, rh.queues, rt.queues, send, reports)
    extras.update({k: v for k, v in rt.extras.items() if not is_channel_stage(k)})
    local = hosted | relayed  # sinks whose figures come from elsewhere
    sink_stages = [s for s in rh.stages + rt.stages if s.name in sinks and s.name not in local]
    sink_queues = [q for q in rh.queues + rt.queues
                   if q.name.rsplit("->", 1)[-1] in sinks and not any(
                       q.name.endswith("->" + h) for h in local)]
    for k in forwards:
        rep = next((r for label, r in zip(labels, reports, strict=True) if label == k.name),
                   {})
        sink_stages += [StageStats(**s) for s in rep.get("stages", [])]
        sink_queues.append(k.stats)
        waited = rh.extras.get(k.name, {}).get("pipeline_waited_s", 0.0)
        extras[k.name] = {**rep.get("extras", {}).get(k.name, {}),
                          "pipeline_waited_s": waited}
    for r in relay_runs:
        rr: PipelineResult = outcome[r.key]
        sink_stages.append(rr.stages[-1])
        sink_queues.append(r.queue_stats(reports))
        extras[r.relay.name] = {**rr.extras.get(r.relay.name, {}),
                                "pipeline_waited_s": round(r.waited_s(reports, rh, rt), 3)}
    return PipelineResult(wall_s=time.perf_counter() - t_start,
                          stages=stages + sink_stages, queues=queues + sink_queues,
                          extras=extras, sinks=sinks)
