"""Stage-to-stage channels between processes: bounded queues of JSON messages.

A channel carries :mod:`sffscan.pipeline.wire` messages (JSON headers; arrays stay in
shared-memory slots) from one process to another through a bounded
``multiprocessing.Queue`` of ``capacity`` messages. :class:`SendStage` is the last stage of
a process's chain: it encodes each item and puts it, blocking while the channel is full
(``block``) or dropping the new item and counting it (``drop_newest``); every wait has a
timeout and re-checks the pipeline's stop flag. :class:`RecvStage` is the first stage of the
next process's chain: it yields the decoded items until the end of stream.
:class:`ForwardSink` taps stages like any sink and sends what it gets to a sink hosted in
its own process. :class:`PooledSource` puts the source's frames into the frame pool.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from typing import Any

import numpy as np
from sffscan.pipeline.queues import PipelineStopped
from sffscan.pipeline.shm_ring import PoolStopped, SlotPool
from sffscan.pipeline.spawn import WAIT_S
from sffscan.pipeline.stats import QueueStats, StageStats
from sffscan.pipeline.wire import decode, discard, encode
from sffscan.stages.frame_source import FrameBuffers
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink, Stage


def is_channel_stage(name: str) -> bool:
    """Whether ``name`` (a stage, a queue ``a->b`` or an extras key) is or names one of a
    channel's stages (``recv:...``, ``send:...``), which the statistics leave out."""
    return "recv:" in name or "send:" in name


def own_stages(stages: Iterable[StageStats], leave_out: Collection[str]) -> list[StageStats]:
    """One process's own stages among ``stages``: without the channels' and the sinks named
    in ``leave_out`` (whose figures come from elsewhere)."""
    return [s for s in stages if not is_channel_stage(s.name) and s.name not in leave_out]


def own_queues(queues: Iterable[QueueStats], leave_out: Collection[str]) -> list[QueueStats]:
    """One process's own queues among ``queues``: without the channels' and those feeding
    the sinks named in ``leave_out``."""
    return [q for q in queues if not is_channel_stage(q.name)
            and q.name.rsplit("->", 1)[-1] not in leave_out]


class _Sender:
    """Puts items into a channel ``q``. With ``precious`` (``drop_newest`` only), ``q``
    holds ``capacity`` items and a reserve above it that only precious items may take:
    the others are dropped once ``capacity`` items wait."""

    def __init__(self, name: str, q: Any, capacity: int, policy: FullPolicy,
                 pools: Sequence[SlotPool], stop: threading.Event,
                 precious: Callable[[Any], bool] | None = None) -> None:
        if policy is FullPolicy.DROP_OLDEST:
            raise ValueError(f"channel '{name}': drop_oldest cannot be done across processes "
                             "(the sender cannot take back a message); use drop_newest")
        self.q = q
        self.pools = pools
        self.stop = stop
        self.policy = policy
        self.capacity = capacity
        self.precious = precious if policy is FullPolicy.DROP_NEWEST else None
        self.stats = QueueStats(name, capacity, policy.value)

    def _over_capacity(self, item: Any) -> bool:
        """Whether a dropping channel with a reserve has no room for ``item``."""
        if self.precious is None or self.precious(item):
            return False
        try:
            return bool(self.q.qsize() >= self.capacity)
        except NotImplementedError:  # macOS: no count, the reserve is anyone's
            return False

    def send(self, item: Any, *, extra: dict[str, Any] | None = None) -> None:
        eos = item is END_OF_STREAM
        dropping = self.policy is FullPolicy.DROP_NEWEST and not eos
        if dropping and self._over_capacity(item):
            self.stats.dropped += 1
            return
        try:
            # a dropping channel does not wait for a slot either: when its arrays find no
            # free slot within one wait (0.25 s), the item is dropped and counted
            data = encode(item, self.pools, (lambda: True) if dropping else self.stop.is_set,
                          extra=extra)
        except PoolStopped:
            if dropping and not self.stop.is_set():
                self.stats.dropped += 1
                return
            raise PipelineStopped(self.stats.name) from None
        if self.policy is FullPolicy.DROP_NEWEST and not eos:
            try:
                self.q.put(data, block=False)
            except queue.Full:
                discard(data, self.pools)
                self.stats.dropped += 1
                return
        else:
            while True:
                if self.stop.is_set():
                    discard(data, self.pools)
                    raise PipelineStopped(self.stats.name)
                try:
                    self.q.put(data, timeout=WAIT_S)
                    break
                except queue.Full:
                    continue
        self.stats.puts += 1
        try:
            fill = self.q.qsize()
        except NotImplementedError:  # macOS
            fill = 0
        self.stats.fill_sum += fill
        self.stats.max_fill = max(self.stats.max_fill, fill)


class SendStage(Stage):
    """Last stage of a process's chain: sends every item to the next process."""

    def __init__(self, name: str, q: Any, *, capacity: int, pools: Sequence[SlotPool],
                 stop: threading.Event, policy: FullPolicy = FullPolicy.BLOCK,
                 count_of: Stage | None = None) -> None:
        self.name = f"send:{name}"
        self._sender = _Sender(name, q, capacity, policy, pools, stop)
        self._count_of = count_of

    @property
    def stats(self) -> QueueStats:
        return self._sender.stats

    def _extra(self) -> dict[str, Any] | None:
        if self._count_of is None:
            return None
        return {"done": getattr(self._count_of, "received", 0)}

    def process(self, item: Any) -> Iterator[Any]:
        self._sender.send(item, extra=self._extra())
        return iter(())

    def finish(self) -> Iterator[Any]:
        self._sender.send(END_OF_STREAM, extra=self._extra())
        return iter(())


class RecvStage(Stage):
    """First stage of a process's chain: the items another process sends, to the end of
    stream. ``received`` counts them; ``done`` is the sender's progress figure."""

    def __init__(self, name: str, q: Any, *, pools: Sequence[SlotPool],
                 stop: threading.Event, producers: int = 1) -> None:
        self.name = f"recv:{name}"
        self.q = q
        self.pools = pools
        self.stop = stop
        self.producers = producers
        self.received = 0
        self.done = 0
        self.ended = 0  # the producers' ends of stream received
        self._ends = threading.Condition()

    def wait_ends(self, n: int) -> bool:
        """Wait until ``n`` producers have ended (True), or the stop flag is set (False)."""
        with self._ends:
            while self.ended < n:
                if self.stop.is_set():
                    return False
                self._ends.wait(WAIT_S)
            return True

    def produce(self) -> Iterator[Any]:
        while self.ended < self.producers:
            try:
                data = self.q.get(timeout=WAIT_S)
            except queue.Empty:
                if self.stop.is_set():
                    raise PipelineStopped(self.name) from None
                continue
            item, extra = decode(data, self.pools)
            self.done = extra.get("done", self.done)
            if item is END_OF_STREAM:
                with self._ends:
                    self.ended += 1
                    self._ends.notify_all()
                continue
            self.received += 1
            yield item


class ForwardSink(Sink):
    """Taps stages like a local sink and forwards the items to a sink in another process.

    ``keep`` (optional) selects the tapped items worth sending (the sink would ignore the
    others): they are left out before anything is copied, and not counted as drops.
    """

    def __init__(self, name: str, taps: tuple[str, ...], q: Any, *, capacity: int,
                 policy: FullPolicy, pools: Sequence[SlotPool], stop: threading.Event,
                 keep: Callable[[Any], bool] | None = None,
                 precious: Callable[[Any], bool] | None = None,
                 channel_capacity: int | None = None) -> None:
        self.name = name
        self.keep = keep
        self.taps = taps
        self.capacity = capacity
        # the local queue blocks; the channel applies the sink's own policy; the precious
        # items (see Sink.precious) make way for themselves in both
        self.policy = FullPolicy.BLOCK if policy is FullPolicy.BLOCK else FullPolicy.DROP_NEWEST
        self.precious = precious
        # its queue's consumer (the sender below) never waits: a precious item waits for
        # room there rather than be dropped, for no longer than a copy into a slot
        self.precious_wait = precious is not None
        self._sender = _Sender(f"{'+'.join(taps)}->{name}", q,
                               capacity if channel_capacity is None else channel_capacity,
                               self.policy, pools, stop, precious)

    @property
    def stats(self) -> QueueStats:
        return self._sender.stats

    def process(self, item: Any) -> Iterator[Any]:
        if self.keep is None or self.keep(item):
            self._sender.send(item)
        return iter(())

    def finish(self) -> Iterator[Any]:
        self._sender.send(END_OF_STREAM)
        return iter(())


class PooledSource(Stage):
    """The source stage, its frames copied once into the frame pool (then passed on by
    reference to every process and sink). A source that writes its frames' pixels itself
    (a replay, a camera, the simulator's render workers: ``inner.buffers``,
    :class:`~sffscan.stages.frame_source.FrameBuffers`) writes them into the pool's slots
    instead, and nothing is copied here."""

    def __init__(self, inner: Stage, pool: SlotPool, stop: threading.Event) -> None:
        self.inner = inner
        self.name = inner.name
        self.unit = inner.unit
        self.pool = pool
        self.stop = stop
        self.buffers: FrameBuffers | None = getattr(inner, "buffers", None)
        if self.buffers is not None:
            self.buffers.bind(self._slot_array)

    def _slot_array(self, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """An array in a free slot of the frame pool (a new one where it would not fit)."""
        if int(np.prod(shape)) * dtype.itemsize > self.pool.spec.slot_bytes:
            return np.empty(shape, dtype)
        try:
            slot = self.pool.acquire(self.stop.is_set)
        except PoolStopped:
            raise PipelineStopped(self.name) from None
        return self.pool.array(slot, offset=0, shape=shape, dtype=dtype.str)

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
        if self.buffers is not None:
            self.buffers.bind(None)
        self.inner.close(failed=failed)

    def extra_stats(self) -> dict[str, Any]:
        return self.inner.extra_stats()
