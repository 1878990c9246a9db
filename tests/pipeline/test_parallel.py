"""Process execution: shared-memory slots, messages, the process runtime and the
simulator's render workers (scans in processes: tests/pipeline/test_parallel_scan.py).
"""


from __future__ import annotations

import gc
import multiprocessing as mp
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sffscan.pipeline.channels import RecvStage, SendStage
from sffscan.pipeline.config import demo_config
from sffscan.pipeline.cores import one_thread_per_process
from sffscan.pipeline.parallel import ProcessPipeline
from sffscan.pipeline.runtime import Pipeline, StageFailed
from sffscan.pipeline.scan_processes import ring_plan, use_processes
from sffscan.pipeline.shm_ring import PoolStopped, SlotPool, new_spec
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.viz.sink import VizSink
from sffscan.pipeline.wire import decode, discard, encode
from sffscan.pipeline.worker import WorkerGroup
from sffscan.stages.messages import (
    DepthBlock,
    DepthBlockHeader,
    FocusFrame,
    Frame,
    FrameHeader,
    PlacedFrame,
)
from sffscan.stages.protocol import END_OF_STREAM, Stage, Tapped

from tests.parallel_helpers import (
    Collect,
    FrameNumbers,
    OpenCVThreads,
    explode_group,
    opencv_threads_group,
    pass_group,
    shm_names,
    thread_mark_group,
)
from tests.scan_helpers import small_config

ROOT = Path(__file__).resolve().parents[2]
CTX = mp.get_context("spawn")


def pool(slots: int = 4, slot_bytes: int = 4096, kinds: tuple[str, ...] = ()) -> SlotPool:
    spec = new_spec("test", slots=slots, slot_bytes=slot_bytes, kinds=kinds)
    return SlotPool(spec, (CTX.Lock(), CTX.Semaphore(slots)), create=True)



# --- slots and messages --------------------------------------------------------------------


def test_slot_is_released_when_its_last_view_is_gone() -> None:
    p = pool()
    try:
        slot = p.acquire(lambda: False)
        a = p.array(slot, offset=0, shape=(8, 8), dtype="<u2")
        part = a[2:5, ::2]  # a view of a view keeps the slot too
        del a
        gc.collect()
        assert p.held() == 1
        del part
        assert p.held() == 0
        # every slot can be taken again, and a full pool waits, then stops on request
        slots = [p.acquire(lambda: False) for _ in range(4)]
        assert sorted(slots) == [0, 1, 2, 3]
        with pytest.raises(PoolStopped):
            p.acquire(lambda: True, wait_s=0.01)
    finally:
        p.close()


def test_messages_round_trip_with_frames_passed_by_reference() -> None:
    frames = pool(slots=4, slot_bytes=64 * 80 * 2, kinds=("frame", "placed"))
    other = pool(slots=4, slot_bytes=1 << 16, kinds=("focus", "block"))
    pools = [frames, other]
    try:
        rng = np.random.default_rng(1)
        img = rng.integers(0, 1024, (64, 80), dtype=np.uint16)
        hdr = FrameHeader(frame_id=7, timestamp_ns=123, focus_index=3, stage_x_um=0.1 + 0.2,
                          stage_y_um=-4.25, pass_index=1)
        # a frame not in a pool is copied into the frame pool (its kind), once
        got, _ = decode(encode(Frame(hdr, img), pools, lambda: False), pools)
        assert got.header == hdr and np.array_equal(got.image, img)
        assert frames.locate(got.image) is not None and frames.held() == 1
        # a placed frame whose image is a view into a slot goes by reference: no new slot
        placed = PlacedFrame(hdr, got.image[:, 5:70], (1.0 / 3.0, 2.5), (10, -3), (0.1, 1e-17))
        back, _ = decode(encode(placed, pools, lambda: False), pools)
        assert frames.held() == 1
        assert back.predicted_px == placed.predicted_px and back.offset_px == (10, -3)
        assert back.correction_px == placed.correction_px
        assert np.array_equal(back.image, img[:, 5:70])
        assert np.shares_memory(back.image, got.image)
        f01 = rng.random((64, 30), dtype=np.float32)
        ff = FocusFrame(placed, f01, f01 * 2, 12)
        b2, _ = decode(encode(Tapped("focus_measure", ff), pools, lambda: False), pools)
        assert b2.stage == "focus_measure" and b2.item.col0 == 12
        assert np.array_equal(b2.item.focus, f01 * 2) and other.held() == 1
        bh = DepthBlockHeader(x0_px=3, y0_px=4, width_px=30, height_px=64, pass_index=0,
                              complete_columns=30, incomplete_columns=0)
        h = np.where(f01 > 0.5, f01, np.nan).astype(np.float32)
        blk, _ = decode(encode(DepthBlock(bh, h, f01, f01), pools, lambda: False), pools)
        assert blk.header == bh and np.array_equal(blk.height_um, h, equal_nan=True)
        eos, extra = decode(encode(END_OF_STREAM, pools, lambda: False, extra={"done": 4}),
                            pools)
        assert eos is END_OF_STREAM and extra == {"done": 4}
        data = encode(Frame(hdr, img), pools, lambda: False)
        discard(data, pools)  # a message not delivered gives its slot back
        del got, back, b2, blk, placed, ff
        gc.collect()
        assert frames.held() == 0 and other.held() == 0
    finally:
        frames.close()
        other.close()


def test_ring_plan_does_not_grow_with_the_scan() -> None:
    short = demo_config(motion={"x_end_mm": 10.0})
    long = demo_config(motion={"x_end_mm": 40.0})
    assert ring_plan(short, []) == ring_plan(long, [])
    (label, slots, slot_bytes, _), (_, bslots, bbytes, _) = ring_plan(long, [])
    # N + 40 + 2 C frame slots of one 1280 x 1024 uint16 frame (module docstring)
    assert (label, slots, slot_bytes) == ("frames", 50 + 40 + 16, 1280 * 1024 * 2)
    assert bslots == 24 and bbytes >= 3 * 1024 * 128 * 4


def test_auto_execution_picks_processes_only_for_large_scans() -> None:
    import rerun as rr

    assert not use_processes(small_config(), [])  # the tests' small scans stay in threads
    big = demo_config()
    assert use_processes(big, []) == ((os.cpu_count() or 1) >= 2)
    assert not use_processes(demo_config(processing={"execution": "threads"}), [])
    # with the live viewer too (it fell back to threads before issue 12's relay)
    rec = rr.RecordingStream("sffscan-test")
    try:
        assert use_processes(big, [VizSink(big, rec)]) == ((os.cpu_count() or 1) >= 2)
    finally:
        rec.disconnect()


def test_simulated_frames_rendered_by_workers_equal_the_serial_ones() -> None:
    from sffscan.pipeline.sim_workers import ParallelSimFrames, noise_steps, parallel_sim_frames

    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 4.0})
    o = cfg.optics
    assert noise_steps(cfg) == o.width_px * o.height_px // 4  # 16-bit noise indices
    serial = list(simulate_frames(cfg))
    par = list(parallel_sim_frames(cfg, workers=3))
    assert [f.header for f in par] == [f.header for f in serial]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(par, serial, strict=True))
    assert not mp.active_children()
    # bound to an allocator (the process placement binds its frame ring's slots), each
    # frame is copied out of its render slot into an array from it, the same values
    bound = ParallelSimFrames(cfg, workers=2)
    handed: list[np.ndarray] = []


    def alloc(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        handed.append(np.empty(shape, dtype))
        return handed[-1]

    bound.buffers.bind(alloc)
    got = list(bound)
    assert len(got) == len(serial) == len(handed)
    assert all(f.image is a and np.array_equal(a, b.image)
               for f, a, b in zip(got, handed, serial, strict=True))
    started = ParallelSimFrames(cfg, workers=2)  # workers start at once ...
    assert len(mp.active_children()) == 2
    started.close()  # ... and stop when closed, never iterated
    assert not mp.active_children()


# --- the process runtime ---------------------------------------------------------------------


def test_a_failing_stage_in_a_worker_stops_every_process_with_its_name() -> None:
    collect = Collect()
    pipe = ProcessPipeline(
        head=[FrameNumbers(200)],
        groups=[WorkerGroup("a", pass_group, {}, ("explode",)),
                WorkerGroup("b", explode_group, {"at": 37},
                            ("explode",))],
        tail=[collect], pools=[("frames", 24, 16 * 24 * 2, ("frame",))], capacity=4)
    with pytest.raises(StageFailed) as info:
        pipe.run()
    assert info.value.stage == "explode"
    assert isinstance(info.value.cause, ValueError)
    assert str(info.value.cause) == "frame_id 37: boom"
    assert collect.closed is True  # the tail was closed as failed
    assert collect.ids == list(range(len(collect.ids))) and len(collect.ids) <= 37
    assert not mp.active_children()
    assert shm_names(os.getpid()) == []


def test_frames_cross_processes_unchanged_and_in_order() -> None:
    collect = Collect()
    result = ProcessPipeline(
        head=[FrameNumbers(300)],
        groups=[WorkerGroup("a", pass_group, {}, ("explode",))],
        tail=[collect], pools=[("frames", 6, 16 * 24 * 2, ("frame",))], capacity=2).run()
    assert collect.ids == list(range(300))
    assert collect.sums == [i * 16 * 24 for i in range(300)]  # 6 slots reused 50 times
    assert collect.closed is False
    assert [s.name for s in result.stages] == ["numbers", "explode", "collect"]
    assert result.extras["processes"]["workers"] == 1
    assert shm_names(os.getpid()) == []


def test_a_process_placement_takes_consecutive_stages_after_the_source() -> None:
    """The placement names the stages each worker builds and runs; they must be a run of
    the pipeline's chain after its source (else nothing starts)."""
    from sffscan.pipeline.parallel import ProcessPlacement
    from sffscan.stages.protocol import FullPolicy

    from tests.parallel_helpers import Explode

    pools: list[tuple[str, int, int, tuple[str, ...]]] = [
        ("frames", 6, 16 * 24 * 2, ("frame",))]
    for placed in (("numbers",), ("collect", "explode"), ("unknown",)):
        pipe = Pipeline([FrameNumbers(3), Collect()], placement=ProcessPlacement(
            [WorkerGroup("a", pass_group, {}, placed)], pools))
        with pytest.raises(ValueError, match="not consecutive stages after the source"):
            pipe.run()
    pipe = Pipeline([FrameNumbers(3), Explode(-1), Collect()],
                    policies={"explode": FullPolicy.DROP_OLDEST}, placement=ProcessPlacement(
                        [WorkerGroup("a", pass_group, {}, ("explode",))], pools))
    with pytest.raises(ValueError, match="blocking queues only"):
        pipe.run()
    assert not mp.active_children()


def test_channel_stages_refuse_drop_oldest() -> None:
    p = pool()
    try:
        from sffscan.stages.protocol import FullPolicy

        with pytest.raises(ValueError, match="drop_oldest"):
            SendStage("x", CTX.Queue(2), capacity=2, pools=[p], stop=__import__(
                "threading").Event(), policy=FullPolicy.DROP_OLDEST)
        assert RecvStage("x", CTX.Queue(2), pools=[p], stop=__import__(
            "threading").Event()).name == "recv:x"
    finally:
        p.close()


# --- the live viewer's relay ---------------------------------------------------------------


def test_relay_forwarder_selects_and_drops_without_waiting() -> None:
    """A dropping forwarder whose arrays find no free slot drops the item and counts it
    (the chain it taps goes on); what ``keep`` leaves out is neither sent nor a drop."""
    import threading

    from sffscan.pipeline.relays import Relay, relay_forwarder
    from sffscan.pipeline.viz.preview import logged_items
    from sffscan.stages.protocol import FullPolicy

    p = pool(slots=1, slot_bytes=4096, kinds=("frame", "placed", "focus"))
    q = CTX.Queue(4)
    try:
        relay = Relay("viewer", ("registration", "focus_measure"), 4, FullPolicy.DROP_OLDEST,
                      (logged_items, {"frame_step": 15}))
        fwd = relay_forwarder(relay, relay.taps, q, pools=[p], stop=threading.Event())
        assert fwd.policy is FullPolicy.DROP_NEWEST
        held = p.acquire(lambda: False)  # every slot held
        img = np.zeros((8, 8), np.uint16)

        def focus(fid: int) -> Tapped:
            placed = PlacedFrame(FrameHeader(frame_id=fid, timestamp_ns=fid, focus_index=0),
                                 img, (0.0, 0.0), (0, 0))
            f = np.ones((8, 4), np.float32)
            return Tapped("focus_measure", FocusFrame(placed, f, f, 4))

        t0 = time.perf_counter()
        list(fwd.process(focus(30)))  # logged (30 % 15 == 0), but no slot: dropped
        assert time.perf_counter() - t0 < 5.0
        list(fwd.process(focus(31)))  # not logged by the view: left out
        assert (fwd.stats.dropped, fwd.stats.puts) == (1, 0)
        keep = logged_items(15)
        assert keep(focus(0)) and not keep(focus(16))
        assert keep(Tapped("depth", None))
        p.decref(held)
        list(fwd.process(focus(45)))  # a slot is free again: sent
        assert (fwd.stats.dropped, fwd.stats.puts) == (1, 1)
        got, _ = decode(q.get(timeout=5), [p])
        assert got.item.placed.header.frame_id == 45 and got.item.col0 == 4
        del got
        gc.collect()
    finally:
        p.close()



def test_relay_channel_keeps_a_reserve_for_the_precious_items() -> None:
    """With ``precious`` (the view's depth blocks), the relay's channel takes other items
    up to its capacity and precious ones into a reserve above it: once the view's channel
    is full of frames, a depth block still gets through; beyond the reserve it drops."""
    import threading

    from sffscan.pipeline.relays import Relay, relay_forwarder
    from sffscan.pipeline.viz.preview import precious_to_view
    from sffscan.stages.protocol import FullPolicy

    p = pool(slots=24, slot_bytes=4096, kinds=("frame", "placed", "block"))
    relay = Relay("viewer", ("registration", "depth"), 2, FullPolicy.DROP_OLDEST,
                  None, precious_to_view)
    assert relay.reserve > 0
    q = CTX.Queue(relay.capacity + relay.reserve)
    try:
        fwd = relay_forwarder(relay, relay.taps, q, pools=[p], stop=threading.Event())
        img = np.zeros((8, 8), np.uint16)
        placed = Tapped("registration", PlacedFrame(
            FrameHeader(frame_id=1, timestamp_ns=1, focus_index=0), img, (0.0, 0.0), (0, 0)))
        f = np.ones((8, 4), np.float32)
        block = Tapped("depth", DepthBlock(DepthBlockHeader(
            x0_px=0, y0_px=0, width_px=4, height_px=8, pass_index=0, complete_columns=4,
            incomplete_columns=0), f, f, f))
        assert precious_to_view(block) and not precious_to_view(placed)
        for item in (placed, placed, placed):  # the third finds the capacity taken
            list(fwd.process(item))
        assert (fwd.stats.puts, fwd.stats.dropped) == (2, 1)
        for _ in range(relay.reserve + 1):  # the reserve's fill, then one dropped
            list(fwd.process(block))
        n = 2 + relay.reserve
        assert (fwd.stats.puts, fwd.stats.dropped) == (n, 2)
        got = [decode(q.get(timeout=5), [p])[0] for _ in range(n)]
        assert [precious_to_view(g) for g in got] == [False] * 2 + [True] * relay.reserve
        del got
        gc.collect()
    finally:
        p.close()


_FAULTS = """
import resource, sys
import numpy as np
from sffscan.pipeline.heap import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def frame():  # a stage's temporaries: three 2.5 MiB arrays alive at once, then freed
    a = np.ones((1024, 640), np.float32)
    b = a * 2
    c = a + b
    return float(c[0, 0])
for _ in range(3):  # warm up
    frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_kept_freed_memory_is_reused_without_page_faults() -> None:
    """What keep_freed_memory is for: a frame's temporaries (three 2.5 MiB arrays alive at
    once, as in the focus measure) fault their pages in again every frame by default (glibc
    trims the freed heap top; 37 760 faults for 20 frames, measured), and are reused once
    the setting took (0)."""
    faults = {}
    for mode in ("default", "keep"):
        done = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True,
                              text=True, timeout=120, check=True)
        faults[mode] = int(done.stdout.split()[-1])
    assert faults["default"] >= 20 * 1000, faults
    assert faults["keep"] <= 200, faults


def test_workers_keep_freed_memory_and_gc_is_thawed_after_a_run() -> None:
    """A worker's glibc settings take (on Linux), in a fresh process so this one keeps its
    own; the main process's objects are back in the collector after a process run."""
    if sys.platform.startswith("linux"):
        code = ("from sffscan.pipeline.heap import keep_freed_memory; "
                "print(keep_freed_memory())")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120, check=True).stdout.split()
        assert out[-1] == "True"
    collect = Collect()
    ProcessPipeline(
        head=[FrameNumbers(40)],
        groups=[WorkerGroup("a", pass_group, {}, ("explode",))],
        tail=[collect], pools=[("frames", 6, 16 * 24 * 2, ("frame",))], capacity=2).run()
    assert collect.ids == list(range(40))
    assert gc.get_freeze_count() == 0
    # threads: frozen while it runs, thawed after
    seen: list[int] = []

    class Probe(Stage):
        name = "probe"

        def process(self, item: Any) -> Iterator[Any]:
            seen.append(gc.get_freeze_count())
            yield item

    tail = Collect()
    Pipeline([FrameNumbers(5), Probe(), tail], capacity=2).run()
    assert tail.ids == list(range(5)) and min(seen) > 0
    assert gc.get_freeze_count() == 0


def test_opencv_runs_one_thread_a_process_where_the_cores_are_few(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """OpenCV's own pool is set to one thread in every process of a process placement (and
    around a thread placement) where the cores available are no more than its parallel
    parts, restored after; left alone with more cores or a user's OPENCV_FOR_THREADS_NUM."""
    import cv2
    from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads

    monkeypatch.delenv("OPENCV_FOR_THREADS_NUM", raising=False)
    default = cv2.getNumThreads()

    def run(cores: int) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
        """(worker's, main process's) threads of a process placement; a thread
        placement's (twice)."""
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
        procs, threads = Collect(), Collect()
        ProcessPipeline(
            head=[FrameNumbers(3)],
            groups=[WorkerGroup("a", opencv_threads_group, {}, ("opencv_threads",))],
            tail=[OpenCVThreads(1, "main"), procs],
            pools=[("frames", 6, 16 * 24 * 2, ("frame",))], capacity=2).run()
        Pipeline([FrameNumbers(3), OpenCVThreads(0), OpenCVThreads(1, "main"), threads],
                 capacity=2).run()
        assert cv2.getNumThreads() == default  # restored after each run
        assert procs.ids == threads.ids == [0, 1, 2]
        return set(procs.corners), set(threads.corners)

    assert run(2) == ({(1, 1)}, {(1, 1)})  # 2 cores: 2 processes, 4 stages
    worker, main = run(64)  # more cores than parts: OpenCV's default (this machine's)
    assert main == {(default, default)}
    assert len(worker) == 1 and next(iter(worker))[1] == default
    assert next(iter(worker))[0] >= 1  # a fresh process's default
    assert opencv_threads(3) is None  # 64 "cores"
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert opencv_threads(3) == 1 and opencv_threads(2) == 1
    monkeypatch.setenv("OPENCV_FOR_THREADS_NUM", "2")
    assert opencv_threads(3) is None
    with opencv_thread_limit(1):
        assert cv2.getNumThreads() == 1
    assert cv2.getNumThreads() == default
    with opencv_thread_limit(None):
        assert cv2.getNumThreads() == default
    # two runs in one process ending out of order (threads of a Dask worker): the first
    # ends while the second runs (still limited), the last restores what was before both
    first, second = opencv_thread_limit(1), opencv_thread_limit(1)
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    assert cv2.getNumThreads() == 1
    second.__exit__(None, None, None)
    assert cv2.getNumThreads() == default


def test_worker_runs_its_stages_in_one_thread_where_cores_are_few(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the cores available are no more than the placement's processes, a worker runs
    its stages in one thread (the same frames either way); with more cores, a thread each."""

    def same_thread(cores: int) -> set[tuple[int, int]]:
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
        tail = Collect()
        ProcessPipeline(head=[FrameNumbers(4)],
                        groups=[WorkerGroup("a", thread_mark_group, {},
                                            ("thread_mark", "same_thread"))],
                        tail=[tail], pools=[("frames", 8, 16 * 24 * 2, ("frame",))],
                        capacity=2,
                        one_thread=one_thread_per_process(2)).run()
        assert tail.ids == [0, 1, 2, 3]
        return set(tail.corners)

    assert same_thread(2) == {(1, 0)}  # 2 cores, 2 processes: one thread
    assert same_thread(3) == {(0, 0)}  # more cores than processes: a thread each



def test_poll_returns_when_a_report_comes_not_at_its_timeout() -> None:
    """The main loop checks the end of the run after each worker message: a poll that
    waited out its timeout held every process-mode run's end (and its wall time, hence
    its frames/s) up to 1 s."""
    import json
    import queue

    from sffscan.pipeline.parallel import _Worker

    workers = [_Worker("a", None, ())]  # type: ignore[arg-type]
    results: queue.Queue[str] = queue.Queue()
    results.put(json.dumps({"label": "a", "kind": "result"}))
    t0 = time.monotonic()
    ProcessPipeline._poll(workers, results, timeout=30.0)
    assert time.monotonic() - t0 < 10.0 and workers[0].report == {"label": "a",
                                                                   "kind": "result"}
