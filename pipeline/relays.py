"""Relays: a sink of the main process fed from stages that run in worker processes.

Each process that runs some of the sink's taps forwards their outputs (a
:class:`~sffscan.pipeline.channels.ForwardSink`, behind a local queue of
:data:`RELAY_LOCAL_CAPACITY`) through one channel to the main process, where the sink runs
behind its own queue and policy, as in the thread runtime (:class:`RelayRun`). The main
process sends the sink the pipeline's statistics too (``wants_stats``), the last ones
after every worker has reported, then the end of stream. Placed frames travel by
reference (the frame ring), other arrays in a slot of a pool taking their kind.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from sffscan.pipeline.channels import ForwardSink, RecvStage
from sffscan.pipeline.queues import offer_stats
from sffscan.pipeline.runtime import Pipeline
from sffscan.pipeline.shm_ring import SlotPool
from sffscan.pipeline.spawn import WAIT_S
from sffscan.pipeline.stats import PipelineResult, QueueStats, StageStats, stats_snapshot
from sffscan.pipeline.wire import encode
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink, Stage

#: queue of a relay's forwarder in each process that taps (the channel applies the policy)
RELAY_LOCAL_CAPACITY = 4
#: a relay's channel, and the queue in front of its sink, hold at most this many items each
RELAY_CAPACITY = 16
#: room in a relay's channel above its capacity that only the sink's precious items take
#: (:attr:`~sffscan.stages.protocol.Sink.precious`; none without them): the view's depth
#: blocks come in bursts at the end of a pass (the frame's width over the block's columns:
#: 10 at the defaults), while its receiver waits for room for them
RELAY_PRECIOUS_RESERVE = 16


@dataclass(frozen=True)
class Relay:
    """A sink of the main process fed from stages in worker processes: each process that
    runs some of ``taps`` forwards their outputs (those ``keep`` selects) through one
    channel to the main process, where the sink runs behind a queue of ``capacity`` items
    with its own ``policy``. The sink's ``precious`` items make way for themselves on the
    way (:attr:`~sffscan.stages.protocol.Sink.precious`), the channel keeping
    :attr:`reserve` places above ``capacity`` for them.

    ``keep`` is ``(factory, kwargs)``: a module-level function (a worker imports it by
    name) returning a predicate on :class:`~sffscan.stages.protocol.Tapped` items, built
    in each process that forwards; or None (all of them).
    """

    name: str
    taps: tuple[str, ...]
    capacity: int
    policy: FullPolicy
    keep: tuple[Callable[..., Callable[[Any], bool]], dict[str, Any]] | None = None
    precious: Callable[[Any], bool] | None = None

    @property
    def reserve(self) -> int:
        """Places in the channel above :attr:`capacity`, for the precious items only."""
        return RELAY_PRECIOUS_RESERVE if self.precious is not None else 0


def relay_of(sink: Any) -> Relay:
    """The relay of a main-process sink: its name, taps and policy, its capacity capped
    at :data:`RELAY_CAPACITY` (what it holds stays in shared-memory slots), and the
    selection it declares as ``relay_keep`` (see :class:`Relay`), if any, and its
    precious items."""
    return Relay(sink.name, tuple(sink.taps), min(sink.capacity, RELAY_CAPACITY),
                 FullPolicy(sink.policy), getattr(sink, "relay_keep", None),
                 sink.precious if sink.policy is not FullPolicy.BLOCK else None)


def relayed_sinks(sinks: list[Sink], head: list[str], tail: list[str]) -> list[Sink]:
    """The main process's sinks that are relayed: those that tap stages other than the
    head's alone or the tail's alone (``head``, ``tail``: the stage names)."""
    return [k for k in sinks if not (set(k.taps) <= set(head) or set(k.taps) <= set(tail))]


def relay_forwarder(relay: Relay, taps: tuple[str, ...], q: Any, *,
                    pools: Sequence[SlotPool], stop: threading.Event) -> ForwardSink:
    """The sink, in one process, that forwards ``taps`` (this process's part of the
    relay's) to the relay's channel ``q``."""
    keep = relay.keep[0](**relay.keep[1]) if relay.keep is not None else None
    return ForwardSink(relay.name, taps, q, capacity=RELAY_LOCAL_CAPACITY,
                       policy=relay.policy, pools=pools, stop=stop, keep=keep,
                       precious=relay.precious, channel_capacity=relay.capacity)


def relay_report(fwd: ForwardSink, result: PipelineResult) -> dict[str, Any]:
    """A relay forwarder's figures: its local queue, its channel, the pipeline's wait."""
    local = next(q for q in result.queues if q.name.rsplit("->", 1)[-1] == fwd.name)
    return {"queue": local.to_json(), "channel": fwd.stats.to_json(),
            "pipeline_waited_s": result.extras.get(fwd.name, {}).get("pipeline_waited_s", 0.0)}


class AfterRelays(Stage):
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
        # ``done`` is set by the main thread whatever happens (the relays' end, a stop)
        while not failed and not self.done.wait(WAIT_S) and not self.failed_elsewhere():
            continue
        self.inner.close(failed=failed or self.failed_elsewhere())

    def extra_stats(self) -> dict[str, Any]:
        return self.inner.extra_stats()


class RelayRun:
    """A relayed sink in the main process: its forwarders in the head and tail, and the
    chain ``recv -> sink`` (the sink behind a queue of the relay's capacity and the sink's
    own policy) that the workers' forwarders, these and the main process feed.

    The producers of the channel are the workers that run some of the taps, the head and
    tail forwarders, and the main process itself, which sends the end of stream once every
    chain has ended (after the last statistics): so the sink ends after everything it taps.
    ``reports`` below are the workers' reports (an empty dict for one not in yet).
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
        # the sink's precious items make way for themselves in its queue, and as the
        # receiver's thread feeds the sink alone, one that finds only precious items there
        # waits for room (the channel behind it fills and its senders drop, never wait)
        self.pipe.queues[0].precious = relay.precious
        self.pipe.queues[0].precious_wait = True

    def queue_stats(self, reports: list[dict[str, Any]]) -> QueueStats:
        """The sink's queue as the summary shows it: the queue in front of the sink, with
        the drops of every forwarder and channel on the way added."""
        own = self.pipe.queues[0].stats
        dropped = own.dropped + sum(f.stats.dropped for f in self.forwards) + sum(
            q.dropped for q in self.local_queues)
        for rep in reports:
            r = (rep.get("relays") or {}).get(self.relay.name)
            if r:
                dropped += r["queue"]["dropped"] + r["channel"]["dropped"]
        return QueueStats(f"{'+'.join(self.relay.taps)}->{self.relay.name}", own.capacity,
                          self.relay.policy.value, own.puts, dropped, own.max_fill,
                          own.fill_sum)

    def bind(self, pipes: list[Pipeline]) -> None:
        """Take the queues of ``pipes`` (head, tail) that feed this relay's forwarders."""
        self.local_queues = [q.stats for p in pipes for q in p.sink_queues
                             if q.name.rsplit("->", 1)[-1] == self.relay.name]

    def snapshot(self, elapsed: float, stages: list[StageStats], queues: list[QueueStats],
                 reports: list[dict[str, Any]], *, last: bool = False) -> None:
        """The pipeline's statistics, this sink's queue last, to the sink if it wants
        them (:func:`~sffscan.pipeline.queues.offer_stats`). The main process is one of
        the channel's producers and sends its end of stream after the last ones
        (:meth:`finish`): none can come after the end of stream."""
        snap = stats_snapshot(elapsed, stages, [*queues, self.queue_stats(reports)])
        offer_stats(self.sink, self.pipe.queues[0], snap, last=last)

    def finish(self, elapsed: float, stages: list[StageStats], queues: list[QueueStats],
               reports: list[dict[str, Any]]) -> None:
        """The last statistics, then the main process's end of stream. The statistics are
        taken once the workers' and the head's items have come out of the channel (each
        item that the sink's queue drops on the way in is then counted in them); the
        tail's forwarder ends only once the relays have (:class:`AfterRelays`)."""
        self.recv.wait_ends(self.recv.producers - 1 - self.in_tail)
        self.snapshot(elapsed, stages, queues, reports, last=True)
        data = encode(END_OF_STREAM, self.pools, lambda: True)
        while True:
            try:
                self.q.put(data, timeout=WAIT_S)
                return
            except queue.Full:
                if self.stop.is_set():
                    return

    def waited_s(self, reports: list[dict[str, Any]], rh: PipelineResult,
                 rt: PipelineResult) -> float:
        """Time the chains waited for this sink (a blocking one falling behind)."""
        name = self.relay.name
        local = sum(r.extras.get(name, {}).get("pipeline_waited_s", 0.0) for r in (rh, rt))
        return local + sum((rep.get("relays") or {}).get(name, {}).get(
            "pipeline_waited_s", 0.0) for rep in reports)
