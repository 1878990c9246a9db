"""The chain in one thread (``Pipeline(one_thread=True)``): the same items, order, end of
stream, statistics and failures as a thread per stage."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from sffscan.pipeline.queues import PipelineStopped
from sffscan.pipeline.runtime import Pipeline, PipelineCancelled, StageFailed
from sffscan.stages.protocol import Stage

from tests.pipeline.test_runtime import (
    Batch,
    Broken,
    Collect,
    Double,
    Explode,
    Numbers,
    Recorder,
)


class Threads(Stage):
    """Passes items on; keeps the threads it ran in and the order of its calls."""

    def __init__(self, name: str, log: list[str]) -> None:
        self.name = name
        self.log = log
        self.idents: set[int] = set()

    def process(self, item: Any) -> Iterator[Any]:
        self.idents.add(threading.get_ident())
        self.log.append(f"{self.name}:{item}")
        yield item

    def finish(self) -> Iterator[Any]:
        self.idents.add(threading.get_ident())
        self.log.append(f"{self.name}:finish")
        return iter(())


@pytest.mark.parametrize("one_thread", [False, True])
def test_same_items_and_statistics_either_way(one_thread: bool) -> None:
    sink = Collect()
    result = Pipeline([Numbers(7), Double(), Batch(), sink], capacity=2,
                      one_thread=one_thread).run()
    assert sink.items == [(0, 2), (4, 6), (8, 10), (12,)]  # the batch's finish flushed
    assert sink.closed_failed is False
    assert [s.frames for s in result.stages] == [7, 7, 7, 4]
    assert [s.items_out for s in result.stages] == [7, 7, 4, 0]
    assert [s.items_in for s in result.stages] == [0, 7, 7, 4]
    assert [q.puts for q in result.queues] == [8, 8, 5]  # the end of stream counted
    if one_thread:  # a hand-over: one item held at each put
        assert all(q.max_fill == 1 and q.fill_sum == q.puts for q in result.queues)


def test_one_thread_runs_every_stage_in_one_thread_item_by_item() -> None:
    log: list[str] = []
    a, b = Threads("a", log), Threads("b", log)
    Pipeline([Numbers(3), a, b, Collect()], one_thread=True).run()
    assert len(a.idents | b.idents) == 1
    assert a.idents != {threading.get_ident()}  # not the caller's thread
    # each item through every stage before the next; a stage's finish after its items,
    # and before the next stage's
    assert log == ["a:0", "b:0", "a:1", "b:1", "a:2", "b:2", "a:finish", "b:finish"]


def test_one_thread_failure_names_the_stage_that_raised() -> None:
    sink = Collect()
    with pytest.raises(StageFailed) as info:
        Pipeline([Numbers(10_000), Double(), Explode(at=100), sink], capacity=4,
                 one_thread=True).run()
    assert info.value.stage == "explode"
    assert "item 100 is bad" in str(info.value)
    assert sink.closed_failed is True
    assert sink.items == list(range(0, 100, 2))  # nothing before the failure was lost


def test_one_thread_failing_finish_and_source_are_named() -> None:
    class BadFinish(Batch):
        name = "flush"

        def finish(self) -> Iterator[tuple[int, ...]]:
            raise OSError("cannot flush")

    with pytest.raises(StageFailed, match="flush.*cannot flush"):
        Pipeline([Numbers(3), BadFinish(), Collect()], one_thread=True).run()
    sink = Collect()
    with pytest.raises(StageFailed, match="camera.*cable unplugged"):
        Pipeline([Broken(), Double(), sink], one_thread=True).run()
    assert sink.items == [2] and sink.closed_failed is True


def test_one_thread_sinks_get_every_tapped_output_in_order() -> None:
    sink = Recorder(delay=threading.Event())
    sink.capacity = 2
    collect = Collect()
    result = Pipeline([Numbers(50), Double(), collect], capacity=4, sinks=[sink],
                      one_thread=True).run()
    assert [v for s, v in sink.got if s == "numbers"] == list(range(50))
    assert [v for s, v in sink.got if s == "double"] == [2 * i for i in range(50)]
    assert collect.items == [2 * i for i in range(50)]
    assert sink.finished and sink.closed_failed is False
    assert result.stages[-1].frames == 100


def test_one_thread_cancel_leaves_a_waiting_source() -> None:
    class Waiting(Stage):
        """A source that waits for items that never come, as a channel's receiver does."""

        name = "recv"

        def __init__(self, stop: threading.Event) -> None:
            self.stop = stop
            self.waiting = threading.Event()

        def produce(self) -> Iterator[int]:
            yield 1
            self.waiting.set()
            while not self.stop.wait(0.05):
                pass
            raise PipelineStopped(self.name)

    stop = threading.Event()
    source, sink = Waiting(stop), Collect()
    pipe = Pipeline([source, Double(), sink], stop=stop, one_thread=True)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            pipe.run()
        except BaseException as exc:  # noqa: BLE001 - checked below
            errors.append(exc)

    t = threading.Thread(target=run)
    t.start()
    assert source.waiting.wait(10)
    pipe.cancel()
    t.join(10)
    assert not t.is_alive()
    assert len(errors) == 1 and isinstance(errors[0], PipelineCancelled)
    assert sink.items == [2] and sink.closed_failed is True


def test_one_thread_stopped_by_a_failing_sink_flushes_nothing() -> None:
    class Flush(Batch):
        def __init__(self) -> None:
            super().__init__()
            self.finished = False

        def finish(self) -> Iterator[tuple[int, ...]]:
            self.finished = True
            return super().finish()

    flush, sink = Flush(), Recorder(fail_at=10)
    with pytest.raises(StageFailed, match="recorder.*disk full"):
        Pipeline([Numbers(10_000), Double(), flush, Collect()], capacity=2, sinks=[sink],
                 one_thread=True).run()
    assert not flush.finished  # a stopped chain ends where it is
    assert sink.closed_failed is True
