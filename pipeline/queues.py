"""Bounded queues between the stages of a pipeline, with a declared full policy.

:class:`BoundedQueue` joins two stages (or a stage and a sink) in the thread runtime
(:mod:`sffscan.pipeline.runtime`): bounded, its policy when full declared (``block``,
``drop_oldest``, ``drop_newest``, every drop counted), every wait with a timeout that
re-checks the pipeline's stop flag (:class:`PipelineStopped` when it is set).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from typing import Any

from sffscan.pipeline.stats import QueueStats, StatsSnapshot
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink


class PipelineStopped(Exception):
    """Raised inside a stage's wait when another stage has failed."""


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
    precious : callable, optional
        Under a dropping policy, the items that other items make way for: a full queue
        discards its oldest item that is not precious instead (``drop_oldest``, or
        ``drop_newest`` when the new item is precious), and a precious item only when
        the queue holds nothing else. It never waits either way.
    precious_wait : bool
        A precious item waits for room instead where nothing else can make way: for a
        queue whose consumer never waits (a relay's forwarder, whose channel drops) or
        whose producer feeds nothing else (a relay's receiver).
    """

    def __init__(
        self,
        name: str,
        capacity: int,
        *,
        policy: FullPolicy = FullPolicy.BLOCK,
        stop: threading.Event | None = None,
        wait_s: float = 0.25,
        precious: Callable[[Any], bool] | None = None,
        precious_wait: bool = False,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"queue '{name}': capacity must be >= 1, got {capacity}")
        self.name = name
        self.capacity = capacity
        self.policy = FullPolicy(policy)
        self.stop = stop if stop is not None else threading.Event()
        self.wait_s = wait_s
        self.precious = precious
        self.precious_wait = precious_wait
        self._items: collections.deque[Any] = collections.deque()
        self._cond = threading.Condition()
        self.stats = QueueStats(name, capacity, self.policy.value)

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: Any, *, keep: bool = False) -> None:
        """Put an item, as the queue's policy says when it is full; with ``keep`` (and for
        the end of stream) wait for room instead, under any policy: nothing is dropped."""
        keep = keep or item is END_OF_STREAM
        with self._cond:
            full = len(self._items) >= self.capacity
            if full and not keep and self.policy is not FullPolicy.BLOCK:
                way = self._make_way(item)
                if way is not None:
                    self.stats.dropped += 1
                    if not way:
                        return
            # block (and a kept item, the end of stream included, under any policy): wait for room
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

    def _make_way(self, item: Any) -> bool | None:
        """In a full dropping queue: discard a held item for ``item`` (True) or not (False:
        ``item`` is the one dropped; None: it waits for room, see ``precious_wait``). The
        end of stream is the last item ever put, so it is never held here."""
        precious = self.precious
        if precious is None:
            if self.policy is FullPolicy.DROP_NEWEST:
                return False
            self._items.popleft()
            return True
        new_precious = precious(item)
        if self.policy is FullPolicy.DROP_OLDEST or new_precious:
            for i, held in enumerate(self._items):
                if not precious(held):  # the oldest that is not precious makes way
                    del self._items[i]
                    return True
        if new_precious and self.precious_wait:
            return None
        if self.policy is FullPolicy.DROP_NEWEST or not new_precious:
            return False  # nothing held is worth less than the new item
        self._items.popleft()
        return True

    def get(self) -> Any:
        with self._cond:
            while not self._items:
                if self.stop.is_set():
                    raise PipelineStopped(self.name)
                self._cond.wait(self.wait_s)
            item = self._items.popleft()
            self._cond.notify_all()
            return item


def offer_stats(sink: Sink, q: BoundedQueue, snap: StatsSnapshot, *, last: bool) -> None:
    """Put ``snap`` into the queue ``q`` of ``sink`` if the sink wants the statistics and
    its queue may drop (a blocking sink's would hold the pipeline back for them).

    The ``last`` statistics wait for room: put into a full queue they would drop its
    oldest item after their copy of the count was taken (one too few)."""
    if sink.wants_stats and q.policy is not FullPolicy.BLOCK:
        q.put(snap, keep=last)
