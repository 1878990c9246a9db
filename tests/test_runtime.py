"""Stage runtime: bounded queues, policies, end of stream, failure propagation."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from pipeline.runtime import (
    END_OF_STREAM,
    BoundedQueue,
    FullPolicy,
    Pipeline,
    PipelineStopped,
    Stage,
    StageFailed,
)


class Numbers(Stage):
    name = "numbers"

    def __init__(self, n: int) -> None:
        self.n = n

    def produce(self) -> Iterator[int]:
        yield from range(self.n)


class Double(Stage):
    name = "double"

    def process(self, item: int) -> Iterator[int]:
        yield 2 * item


class Batch(Stage):
    """Holds items and releases them in pairs; flushes the odd one at end of stream."""

    name = "batch"

    def __init__(self) -> None:
        self.held: list[int] = []

    def process(self, item: int) -> Iterator[tuple[int, ...]]:
        self.held.append(item)
        if len(self.held) == 2:
            yield tuple(self.held)
            self.held = []

    def finish(self) -> Iterator[tuple[int, ...]]:
        if self.held:
            yield tuple(self.held)


class Collect(Stage):
    name = "collect"

    def __init__(self) -> None:
        self.items: list[Any] = []
        self.closed_failed: bool | None = None

    def process(self, item: Any) -> Iterator[None]:
        self.items.append(item)
        return iter(())

    def close(self, *, failed: bool) -> None:
        self.closed_failed = failed


class Explode(Stage):
    name = "explode"

    def __init__(self, at: int) -> None:
        self.at = at

    def process(self, item: int) -> Iterator[int]:
        if item == self.at:
            raise ValueError(f"item {item} is bad")
        yield item


def test_items_flow_in_order_and_end_of_stream_flushes() -> None:
    sink = Collect()
    result = Pipeline([Numbers(7), Double(), Batch(), sink], capacity=2).run()
    assert sink.items == [(0, 2), (4, 6), (8, 10), (12,)]
    assert sink.closed_failed is False
    assert [s.frames for s in result.stages] == [7, 7, 7, 4]
    assert result.dropped == 0
    assert all(q.max_fill <= 2 for q in result.queues)


def test_failing_stage_stops_pipeline_with_its_name_and_cause() -> None:
    sink = Collect()
    with pytest.raises(StageFailed) as info:
        Pipeline([Numbers(10_000), Explode(at=50), sink], capacity=4).run()
    assert info.value.stage == "explode"
    assert isinstance(info.value.cause, ValueError)
    assert "item 50 is bad" in str(info.value)
    assert sink.closed_failed is True  # every stage was closed, told of the failure
    assert sink.items == list(range(50))  # nothing before the failure was lost


def test_failing_source_is_reported() -> None:
    class Broken(Stage):
        name = "camera"

        def produce(self) -> Iterator[int]:
            yield 1
            raise OSError("cable unplugged")

    sink = Collect()
    with pytest.raises(StageFailed, match="camera.*cable unplugged"):
        Pipeline([Broken(), sink]).run()
    assert sink.items == [1]


def test_block_policy_waits_for_room_and_never_drops() -> None:
    q = BoundedQueue("q", 1)
    q.put(1)
    got: list[int] = []
    t = threading.Thread(target=lambda: got.append(q.get()))
    q2_done = threading.Event()

    def producer() -> None:
        q.put(2)  # blocks until the consumer took 1
        q2_done.set()

    p = threading.Thread(target=producer)
    p.start()
    assert not q2_done.wait(0.3)
    t.start()
    t.join(5)
    p.join(5)
    assert got == [1] and q2_done.is_set() and q.get() == 2
    assert q.stats.dropped == 0


@pytest.mark.parametrize(("policy", "kept"), [(FullPolicy.DROP_OLDEST, [3, 4]),
                                              (FullPolicy.DROP_NEWEST, [1, 2])])
def test_drop_policies_count_what_they_drop(policy: FullPolicy, kept: list[int]) -> None:
    q = BoundedQueue("viz", 2, policy=policy)
    for i in (1, 2, 3, 4):
        q.put(i)
    assert [q.get(), q.get()] == kept
    q.put(5)
    q.put(6)
    done = threading.Event()
    t = threading.Thread(target=lambda: (q.put(END_OF_STREAM), done.set()))
    t.start()
    assert not done.wait(0.3)  # the end of stream is never dropped: it waits for room
    got = [q.get(), q.get()]
    t.join(5)
    assert q.get() is END_OF_STREAM and done.is_set()
    assert len(got) == 2
    assert q.stats.dropped == 2


def test_waits_leave_when_pipeline_stops() -> None:
    stop = threading.Event()
    q = BoundedQueue("q", 1, stop=stop, wait_s=0.05)
    stop.set()
    with pytest.raises(PipelineStopped):
        q.get()
    q.put(1)
    with pytest.raises(PipelineStopped):
        q.put(2)


def test_bad_pipeline_definitions() -> None:
    with pytest.raises(ValueError, match="capacity"):
        BoundedQueue("q", 0)
    with pytest.raises(ValueError, match="unique"):
        Pipeline([Numbers(1), Double(), Double()])


def test_progress_display_failing_stops_and_closes_everything() -> None:
    sink = Collect()

    def progress(stats, elapsed):  # noqa: ANN001
        raise BrokenPipeError("stderr closed")

    class Slow(Stage):
        name = "slow"

        def __init__(self) -> None:
            self.stop = threading.Event()

        def produce(self) -> Iterator[int]:
            for i in range(1000):
                self.stop.wait(0.01)
                yield i

    pipe = Pipeline([Slow(), sink], on_progress=progress, progress_s=0.05)
    with pytest.raises(BrokenPipeError):
        pipe.run()
    assert pipe.stop.is_set()
    assert sink.closed_failed is True
