"""Stage runtime: bounded queues, policies, end of stream, failure propagation."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from sffscan.pipeline.queues import BoundedQueue, PipelineStopped
from sffscan.pipeline.runtime import Pipeline, StageFailed
from sffscan.stages.protocol import END_OF_STREAM, FullPolicy, Sink, Stage, Tapped


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


def test_stages_prepare_before_the_stream_and_a_failure_is_named() -> None:
    class Prepared(Double):
        def __init__(self, fail: bool) -> None:
            self.fail = fail
            self.seen: list[int] = []

        def prepare(self) -> None:
            if self.fail:
                raise MemoryError("no room for the ring")
            self.seen.append(-1)

        def process(self, item: int) -> Iterator[int]:
            self.seen.append(item)
            return super().process(item)

    ok = Prepared(False)
    pipe = Pipeline([Numbers(3), ok, Collect()])
    pipe.prepare()  # as a worker does before it reports ready
    pipe.run()
    assert ok.seen == [-1, 0, 1, 2]  # once, before the first item
    sink = Collect()
    with pytest.raises(StageFailed, match="double.*no room for the ring"):
        Pipeline([Numbers(3), Prepared(True), sink]).run()
    assert sink.items == [] and sink.closed_failed is True


class Broken(Stage):
    """A source that yields one item, then fails."""

    name = "camera"

    def produce(self) -> Iterator[int]:
        yield 1
        raise OSError("cable unplugged")


def test_failing_source_is_reported() -> None:
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


def test_precious_items_go_last_and_never_make_a_dropping_queue_wait() -> None:
    """``precious`` (the live view's depth blocks): a full dropping queue discards its
    oldest other item for a precious one, a precious one only when it holds nothing else,
    and a new ordinary item rather than a held precious one; it never waits."""
    def precious(item: object) -> bool:
        return isinstance(item, str)

    stopped = threading.Event()
    stopped.set()  # a put that would wait raises PipelineStopped instead
    q = BoundedQueue("viz", 3, policy=FullPolicy.DROP_OLDEST, precious=precious, stop=stopped)
    for item in (1, "a", 2, 3, "b"):  # 1 makes way for 3, 2 for "b"
        q.put(item)
    assert list(q._items) == ["a", 3, "b"] and q.stats.dropped == 2
    q.put("c")  # 3, the only ordinary item, makes way
    q.put(4)  # everything held is precious: the new ordinary item is the one dropped
    assert list(q._items) == ["a", "b", "c"] and q.stats.dropped == 4
    q.put("d")  # all precious: the oldest goes, as without ``precious``
    assert list(q._items) == ["b", "c", "d"] and q.stats.dropped == 5

    n = BoundedQueue("viz", 2, policy=FullPolicy.DROP_NEWEST, precious=precious, stop=stopped)
    for item in (1, 2, 3, "a", "b", "c"):  # 3 dropped; 1 and 2 make way for "a" and "b"
        n.put(item)
    assert list(n._items) == ["a", "b"] and n.stats.dropped == 4  # and "c" is dropped
    assert n.stats.puts == 4

    # precious_wait (a relay's own queues): where nothing else can make way, a precious
    # item waits for room, and is not counted as dropped
    w = BoundedQueue("relay", 2, policy=FullPolicy.DROP_OLDEST, precious=precious,
                     precious_wait=True)
    for item in ("a", 1, "b"):  # 1 makes way for "b"
        w.put(item)
    w.put(2)  # nothing held is worth less: 2 is dropped
    assert list(w._items) == ["a", "b"] and w.stats.dropped == 2
    done = threading.Event()
    t = threading.Thread(target=lambda: (w.put("c"), done.set()))
    t.start()
    assert not done.wait(0.3)
    assert w.get() == "a"
    t.join(5)
    assert done.is_set() and list(w._items) == ["b", "c"] and w.stats.dropped == 2
    f = BoundedQueue("forwarder", 1, policy=FullPolicy.DROP_NEWEST, precious=precious,
                     precious_wait=True)
    f.put("a")
    done.clear()
    t = threading.Thread(target=lambda: (f.put("b"), done.set()))
    t.start()
    assert not done.wait(0.3)
    assert f.get() == "a"
    t.join(5)
    assert done.is_set() and f.get() == "b" and f.stats.dropped == 0


@pytest.mark.parametrize("policy", [FullPolicy.DROP_OLDEST, FullPolicy.DROP_NEWEST])
def test_kept_item_waits_for_room_under_a_drop_policy(policy: FullPolicy) -> None:
    """The last statistics to a dropping viewer: put with ``keep``, nothing is dropped (the
    count they carry stays the final one)."""
    q = BoundedQueue("viz", 2, policy=policy)
    q.put(1)
    q.put(2)
    done = threading.Event()
    t = threading.Thread(target=lambda: (q.put("last", keep=True), done.set()))
    t.start()
    assert not done.wait(0.3)
    assert q.get() == 1
    t.join(5)
    assert done.is_set() and [q.get(), q.get()] == [2, "last"]
    assert q.stats.dropped == 0


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


class Recorder(Sink):
    """A sink that keeps what it receives (optionally slowly, or failing at an item)."""

    name = "recorder"
    taps = ("numbers", "double")

    def __init__(self, *, delay: threading.Event | None = None, fail_at: int = -1) -> None:
        self.got: list[tuple[str, Any]] = []
        self.finished = False
        self.closed_failed: bool | None = None
        self.delay = delay
        self.fail_at = fail_at

    def process(self, item: Tapped) -> Iterator[Any]:
        if self.delay is not None:
            self.delay.wait(0.002)
        if len(self.got) == self.fail_at:
            raise OSError("disk full")
        self.got.append((item.stage, item.item))
        return iter(())

    def finish(self) -> Iterator[Any]:
        self.finished = True
        return iter(())

    def close(self, *, failed: bool) -> None:
        self.closed_failed = failed


def test_sink_receives_every_tapped_output_in_order_then_finishes() -> None:
    sink = Recorder(delay=threading.Event())
    sink.capacity = 2  # small: the chain must wait for it, and the wait is reported
    collect = Collect()
    result = Pipeline([Numbers(50), Double(), collect], capacity=4, sinks=[sink]).run()
    assert [v for s, v in sink.got if s == "numbers"] == list(range(50))
    assert [v for s, v in sink.got if s == "double"] == [2 * i for i in range(50)]
    assert collect.items == [2 * i for i in range(50)]
    assert sink.finished and sink.closed_failed is False
    assert result.extras["recorder"]["pipeline_waited_s"] > 0
    assert [s.name for s in result.stages][-1] == "recorder"
    assert result.stages[-1].frames == 100


def test_failing_sink_stops_the_pipeline_with_its_name() -> None:
    sink = Recorder(fail_at=10)
    with pytest.raises(StageFailed, match="recorder.*disk full"):
        Pipeline([Numbers(1000), Double(), Collect()], capacity=2, sinks=[sink]).run()
    assert sink.closed_failed is True
    assert len(sink.got) == 10


def test_dropping_sink_never_holds_the_chain_and_counts_drops() -> None:
    sink = Recorder(delay=threading.Event())
    sink.capacity, sink.policy = 1, FullPolicy.DROP_OLDEST
    collect = Collect()
    result = Pipeline([Numbers(300), Double(), collect], capacity=4, sinks=[sink]).run()
    assert collect.items == [2 * i for i in range(300)]
    sink_q = result.queues[-1]
    assert sink_q.dropped > 0
    assert len(sink.got) + sink_q.dropped == 600


def test_sink_tapping_an_unknown_stage_is_refused() -> None:
    sink = Recorder()
    sink.taps = ("nope",)
    with pytest.raises(ValueError, match="unknown stages"):
        Pipeline([Numbers(3), Collect()], sinks=[sink])
