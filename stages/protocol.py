"""The stage protocol: what a stage, a sink and the end of stream are.

A stage turns one input item into zero or more outputs (:meth:`Stage.process`), flushes
what it holds at the end of stream (:meth:`Stage.finish`) and releases its resources
(:meth:`Stage.close`). This module is the contract between the computation (``stages``)
and the runtime that runs it (``sffscan.pipeline.runtime``: threads or worker processes,
bounded queues, statistics); it imports nothing from either.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any


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

    def prepare(self) -> None:
        """Allocate (and touch) what the stream will need, before its first item: called
        once before the pipeline starts (in a worker process: before it reports ready), so
        that no frame waits for it. Default: nothing."""
        return None

    def close(self, *, failed: bool) -> None:
        return None

    def extra_stats(self) -> dict[str, Any]:
        """Stage-specific figures for the summary (dropped frames, corrections, ...)."""
        return {}


@dataclass(frozen=True, slots=True)
class Tapped:
    """An output of stage ``stage``, as a sink receives it (``item`` is shared: read only)."""

    stage: str
    item: Any


class Sink(Stage):
    """A side branch: consumes :class:`Tapped` outputs of the stages named in ``taps``.

    A sink implements :meth:`Stage.process` (its outputs are discarded), :meth:`finish`
    and :meth:`close` like any stage. If it raises, the pipeline stops like for any stage.
    """

    #: Names of the stages whose outputs this sink receives.
    taps: tuple[str, ...] = ()
    #: Capacity and full policy of the sink's own input queue.
    capacity: int = 64
    policy: FullPolicy = FullPolicy.BLOCK
    #: Under a dropping policy, the items dropped only when the queue holds nothing else
    #: (the others go first): a module-level predicate on :class:`Tapped` items (worker
    #: processes import it), set on the instance (a class attribute would bind it as a
    #: method). None: every item alike.
    precious: Callable[[Any], bool] | None = None
    #: A precious item waits for room in the sink's queue where nothing else can make way
    #: (only for a sink whose own consumer never waits: a relay's forwarder).
    precious_wait: bool = False
    #: Receive a :class:`StatsSnapshot` about every ``progress_s`` seconds.
    wants_stats: bool = False
    unit = "items"
