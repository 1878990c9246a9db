"""Band processes (issue 28): the focus volume's rows split among K processes sharing its
state; blocks bit-identical to one band, failures named, nothing left behind."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sffscan.pipeline.band_processes import (
    BandProcesses,
    BandProcessFailed,
    LazyBandProcesses,
)
from sffscan.stages.bands import BandTaskThreads
from sffscan.stages.depth_stage import DepthStage
from sffscan.stages.focus_measure import FocusMeasureStage
from sffscan.stages.focus_volume import FocusVolume
from sffscan.stages.messages import FrameError, FrameHeader, PlacedFrame
from sffscan.stages.shared_volume import SharedFocusVolume
from sffscan.stages.volume_tasks import RAW_SLOTS, run_task

from tests.stages.test_focus_volume import (
    HEIGHTS,
    H,
    N,
    W,
    assert_same_blocks,
    wobbly_frames_into,
)

# what _wobbly_scan builds its volume with
VOLUME = dict(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
              median_size=3, block_columns=16, row_slack=3, spread_size=3)


def _segments() -> set[str]:
    shm = Path("/dev/shm")
    return {p.name for p in shm.iterdir() if p.name.startswith(f"sffscan-{os.getpid()}-")} \
        if shm.is_dir() else set()


def _passes(method: str, direction: int, workers: BandProcesses | None) -> list:
    """The blocks of two passes of _wobbly_scan's frames, the second volume taking over the
    first's ring (as the depth stage does), the first pass from a new volume."""
    out, vol = [], None
    for _ in range(2):
        if workers is None:
            vol = FocusVolume(direction=direction, method=method, reuse=vol,
                              **VOLUME)  # type: ignore[arg-type]
        else:
            vol = SharedFocusVolume(direction=direction, method=method, reuse=vol,
                                    workers=workers, **VOLUME)
        out += wobbly_frames_into(vol, direction)
    return out


@pytest.mark.parametrize(("method", "direction"), [
    ("shape_select", 1), ("shape_select", -1), ("spc", 1), ("centroid", -1),
    ("wcentroid", 1), ("gauss3", 1)])
def test_blocks_are_bit_identical_in_band_processes(method: str, direction: int) -> None:
    """Three bands (two helper processes) and one band in the shared arrays give every
    block bit for bit as the volume alone: wobble, ties, partial columns, a dropped frame,
    the ring wrapping, both directions, a second pass that takes over the first's ring;
    the streaming sums and the N-level ring."""
    alone = _passes(method, direction, None)
    assert sum(b.complete for b in alone) > 200
    layout = SharedFocusVolume.shared_layout(method=method, **VOLUME)
    with BandProcesses(3, layout, name="test-band") as pool:
        assert_same_blocks(alone, _passes(method, direction, pool))
        assert pool.helpers_cpu_s() > 0
        assert_same_blocks(alone, _passes(method, direction, pool))  # the arrays used before
    with BandProcesses(1, layout) as one:
        assert_same_blocks(alone, _passes(method, direction, one))
    assert not _segments()


def test_a_failing_band_process_names_itself_and_the_rows() -> None:
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    with BandProcesses(2, layout, name="test-fail") as pool:
        assert not _segments()  # unlinked once the helper mapped it
        # level 99 of 12: only the helper's band has rows to write
        bad = {"writes": [[99, 0, 0, 0, 10, 0, 4]], "shape": [10, 4], "cache_bytes": 1 << 19,
               "low": False}
        with pytest.raises(BandProcessFailed, match=r"sffscan-test-fail-1 \(accumulate, rows "
                           r"5\.\.10\): IndexError: index 99 is out of bounds"):
            pool.run_task("accumulate", bad, [(0, 0), (5, 10)])
        with pytest.raises(ValueError, match="unknown band task 'nonsense'"):
            pool.run_task("nonsense", {}, [(0, 5), (5, 10)])  # the caller's own band first
        # still answers after an error
        assert_same_blocks(_passes("spc", 1, None), _passes("spc", 1, pool))
        os.kill(pool._procs[0].pid, signal.SIGKILL)
        pool._procs[0].join(10)
        with pytest.raises(BandProcessFailed, match="sffscan-test-fail-1 .* died"):
            _passes("spc", 1, pool)
    pool.close()  # idempotent
    assert not pool._procs


def test_a_submitted_task_that_fails_is_raised_by_the_wait_that_reaches_it() -> None:
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    bad = {"writes": [[99, 0, 0, 0, 10, 0, 4]], "shape": [10, 4], "cache_bytes": 1 << 19,
           "low": False}
    good = {**bad, "writes": [[1, 0, 0, 0, 10, 0, 4]]}
    with BandProcesses(2, layout, name="test-async") as pool:
        first = pool.submit_task("accumulate", good, [(0, 0), (5, 10)])
        second = pool.submit_task("accumulate", bad, [(0, 0), (5, 10)])  # returns at once
        assert second == first + 1
        pool.wait_tasks(first)  # the good one
        with pytest.raises(BandProcessFailed, match=r"sffscan-test-async-1 \(accumulate, "
                           r"rows 5\.\.10\): IndexError"):
            pool.wait_tasks()
        pool.wait_tasks()  # nothing left to wait for
        pool.submit_task("accumulate", bad, [(0, 0), (5, 10)])
    # closed with a failed task outstanding: waited for, not raised, nothing left behind
    assert not pool._procs and not _segments()


def test_a_helper_that_does_not_answer_is_waited_for_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Three tasks outstanding on a stopped helper: one timeout fails the wait (not one a
    task), and the pool still closes."""
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    good = {"writes": [[1, 0, 0, 0, 10, 0, 4]], "shape": [10, 4], "cache_bytes": 1 << 19,
            "low": False}
    pool = BandProcesses(2, layout, name="test-stopped", timeout_s=0.5)
    waits: list[str] = []
    receive = pool._receive

    def counted(i: int, timeout_s: float, what: str) -> dict:
        waits.append(what)
        return receive(i, timeout_s, what)

    monkeypatch.setattr(pool, "_receive", counted)
    helper = pool._procs[0]
    os.kill(helper.pid, signal.SIGSTOP)
    try:
        for _ in range(3):
            pool.submit_task("accumulate", good, [(0, 0), (5, 10)])
        with pytest.raises(BandProcessFailed, match=r"sffscan-test-stopped-1 \(accumulate, "
                           r"rows 5\.\.10\) did not answer within 0\.5 s"):
            pool.wait_tasks()
        assert len(waits) == 1
    finally:
        os.kill(helper.pid, signal.SIGCONT)
        pool.close()
    assert not pool._procs and not _segments()


def test_a_volume_refuses_arrays_laid_out_for_another() -> None:
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    with BandProcesses(1, layout) as pool, pytest.raises(ValueError, match="laid out for"):
        SharedFocusVolume(method="gauss3", workers=pool, **VOLUME)
    assert "fv" not in layout  # SPC keeps sums, no N-level ring


def _raw_scan(n: int = 48) -> list[PlacedFrame]:
    """Two passes (+x, then -x) of random 10-bit frames that wobble across the motion."""
    rng = np.random.default_rng(7)
    out = []
    for k in range(2 * n):
        p, j = divmod(k, n)
        x = 100 + 4 * j if p == 0 else 100 + 4 * (n - j)
        y = 10 + (k * 7) % 5 - 2
        hdr = FrameHeader(frame_id=k, timestamp_ns=k, focus_index=k % N, pass_index=p)
        img = rng.integers(0, 1024, (H, W), dtype=np.uint16)
        out.append(PlacedFrame(hdr, img, (float(x), float(y)), (x, y)))
    return out


# the depth stage of _raw_scan's frames
RAW_DEPTH = dict(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                 median_size=3, block_columns=16, slack_px=3, spread_size=3,
                 directions=(1, -1))


def _raw_blocks(method: str, bands: Any = None) -> list:
    """The focus measure and depth stages' blocks of _raw_scan's frames; with ``bands``
    (band tasks) those measure the focus (RawColumns), and are closed after."""
    fm = FocusMeasureStage(operator="glvm", window=5, max_value=1023.0, margin=3,
                           directions=(1, -1), bands_measure=bands is not None)
    depth = DepthStage(band_tasks=bands, **{**RAW_DEPTH, "method": method})  # type: ignore[arg-type]
    depth.prepare()
    try:
        out = [b for q in _raw_scan() for f in fm.process(q) for b in depth.process(f)]
        return out + list(depth.finish())
    finally:
        depth.close(failed=False)


def assert_same_depth_blocks(ref: list, got: list) -> None:
    """The depth stage's blocks, header and every array, bit for bit."""
    assert len(got) == len(ref)
    for a, b in zip(ref, got, strict=True):
        assert a.header == b.header
        for u, v in ((a.height_um, b.height_um), (a.texture, b.texture),
                     (a.confidence, b.confidence), (a.uncertainty_um, b.uncertainty_um)):
            assert u.tobytes() == v.tobytes()


@pytest.mark.parametrize("method", ["shape_select", "spc"])
def test_band_processes_measure_what_they_add(method: str) -> None:
    """Each band process measuring the focus of its own rows (the focus measure stage
    passing RawColumns on, SharedFocusVolume.add_raw: one task a frame) gives the blocks of
    the focus measure and depth stages in one process, bit for bit, both directions."""
    frames = _raw_scan()
    kw = {**RAW_DEPTH, "method": method}

    def focus(band_processes: bool = False) -> FocusMeasureStage:
        return FocusMeasureStage(operator="glvm", window=5, max_value=1023.0, margin=3,
                                 directions=(1, -1), bands_measure=band_processes)

    fm, depth = focus(), DepthStage(**kw)  # type: ignore[arg-type]
    ref = [b for q in frames for f in fm.process(q) for b in depth.process(f)]
    ref += list(depth.finish())
    assert sum(b.header.complete_columns for b in ref) > 200
    layout = SharedFocusVolume.shared_layout(**{**kw, "row_slack": 3, "col_slack": 3})
    for k in (1, 3):
        pool = LazyBandProcesses(k, layout, name="test-raw")
        fm, depth = focus(True), DepthStage(band_tasks=pool, **kw)  # type: ignore[arg-type]
        depth.prepare()
        try:
            got = [b for q in frames for f in fm.process(q) for b in depth.process(f)]
            got += list(depth.finish())
        finally:
            depth.close(failed=False)
        assert_same_depth_blocks(ref, got)
        with pytest.raises(BandProcessFailed, match="used after they were closed"):
            pool.run_task("depth", {}, [(0, 1)])
    assert not _segments()


class DeferredBands:
    """Band tasks whose helpers run as late as they may: the caller's band at once, the
    others only when their ticket is waited for (in order). A volume that read or
    overwrote the shared arrays before waiting would get other blocks."""

    def __init__(self, k: int, layout: dict) -> None:
        self.k = k
        self.arrays = {name: np.zeros(shape, dtype) for name, (shape, dtype) in layout.items()}
        self.queue: list[tuple[int, str, dict, list[tuple[int, int]]]] = []
        self.ticket = self.most_behind = 0

    def submit_task(self, task: str, params: dict, bands: list[tuple[int, int]]) -> int:
        self.ticket += 1
        params = json.loads(json.dumps(params))  # as sent down a pipe: a copy
        run_task(self.arrays, task, params, bands[0])
        self.queue.append((self.ticket, task, params, bands[1:]))
        self.most_behind = max(self.most_behind, len(self.queue))
        return self.ticket

    def wait_tasks(self, ticket: int | None = None) -> None:
        while self.queue and (ticket is None or self.queue[0][0] <= ticket):
            _, task, params, rest = self.queue.pop(0)
            for rows in rest:
                run_task(self.arrays, task, params, rows)

    def run_task(self, task: str, params: dict, bands: list[tuple[int, int]]) -> None:
        self.wait_tasks(self.submit_task(task, params, bands))

    def helpers_cpu_s(self) -> float:
        return 0.0

    def close(self) -> None:
        self.wait_tasks()


@pytest.mark.parametrize("method", ["shape_select", "spc"])
def test_frames_go_to_the_bands_without_waiting_for_them(method: str) -> None:
    """add_raw submits each frame's task and goes on (the bands up to RAW_SLOTS - 1 frames
    behind), waiting only before a block or before a raw slot is used again: with helpers
    that run as late as that allows, the blocks are still those of one process, bit for
    bit, both directions."""
    ref = _raw_blocks(method)
    layout = SharedFocusVolume.shared_layout(**{**RAW_DEPTH, "method": method,
                                                "row_slack": 3, "col_slack": 3})
    bands = DeferredBands(3, layout)
    got = _raw_blocks(method, bands)
    assert bands.most_behind == RAW_SLOTS  # frames were measured behind the caller
    assert_same_depth_blocks(ref, got)


def test_a_frame_to_measure_needs_band_processes() -> None:
    fm = FocusMeasureStage(operator="glvm", window=5, max_value=1023.0, margin=3,
                           bands_measure=True)
    depth = DepthStage(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                       median_size=3, block_columns=16, slack_px=3, spread_size=3)
    item = next(iter(fm.process(_raw_scan(2)[0])))
    with pytest.raises(FrameError, match="frame_id 0: a frame to measure .* needs the depth "
                       "stage's band workers"):
        list(depth.process(item))
    with pytest.raises(ValueError, match="OpenCV backend only"):
        FocusMeasureStage(margin=3, backend="torch", bands_measure=True)


def test_band_workers_are_chosen_by_the_configuration(tmp_path: Path) -> None:
    """processing.bands = 'processes' builds both stages on one set of band processes,
    'threads' on band task threads (for more than one band only, the OpenCV backend: with
    torch the focus measure's own threads and the volume's band threads); 'processes'
    refuses the torch backend, and the live view never asks for a frame the bands
    measure."""
    from sffscan.pipeline.config import ConfigError, ScanConfig, load_config
    from sffscan.pipeline.measuring import measure_stages
    from sffscan.pipeline.viz.preview import logged_items

    from tests.scan_helpers import small_config

    fm, depth = measure_stages(small_config(processing={"workers": 2, "bands": "processes"}),
                               only=("focus_measure", "depth"))
    assert isinstance(fm, FocusMeasureStage) and fm.bands_measure
    assert isinstance(depth, DepthStage) and isinstance(depth.band_tasks, LazyBandProcesses)
    assert depth.band_tasks.k == 2
    fm, depth = measure_stages(small_config(processing={"workers": 3, "bands": "threads"}),
                               only=("focus_measure", "depth"))
    assert isinstance(fm, FocusMeasureStage) and fm.bands_measure
    assert isinstance(depth, DepthStage) and isinstance(depth.band_tasks, BandTaskThreads)
    assert depth.band_tasks.k == 3
    depth.close(failed=False)
    for cfg in (small_config(processing={"workers": 1, "bands": "processes"}),
                small_config(processing={"workers": 2, "backend": "torch"})):
        fm, depth = measure_stages(cfg, only=("focus_measure", "depth"))
        assert not fm.bands_measure and depth.band_tasks is None  # type: ignore[attr-defined]
    fm, = measure_stages(small_config(processing={"workers": 2, "bands": "processes"}),
                         only=("focus_measure",))
    assert not fm.bands_measure  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="bands = 'processes' measures the focus with the "
                       "OpenCV backend; backend is 'torch'"):
        ScanConfig.model_validate({"processing": {"bands": "processes", "backend": "torch"}})
    bad = tmp_path / "bad.toml"
    bad.write_text('[processing]\nbands = "processes"\nbackend = "torch"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match="processing.*OpenCV backend"):
        load_config(bad)
    item = next(iter(FocusMeasureStage(margin=3, bands_measure=True, max_value=1023.0)
                     .process(_raw_scan(2)[0])))
    assert not logged_items(1)(item)


def test_band_processes_refuse_a_segment_the_shared_memory_cannot_hold(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from sffscan.pipeline import band_processes as bp

    class Small:
        f_bavail, f_frsize = 10, 4096  # 40 KiB free

    monkeypatch.setattr(bp.os, "statvfs", lambda _folder: Small())
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    with pytest.raises(BandProcessFailed, match=r"need \d+ MiB of shared memory, /dev/shm has "
                       r"0 MiB free .*processing.bands = 'threads'"):
        BandProcesses(2, layout)
    assert not _segments()


# -- the same tasks in threads (processing.bands = "threads") --------------------------------

@pytest.mark.parametrize(("method", "direction"), [
    ("shape_select", 1), ("shape_select", -1), ("spc", 1), ("gauss3", -1)])
def test_blocks_are_bit_identical_in_band_task_threads(method: str, direction: int) -> None:
    """Three band task threads give every block of two passes (the second taking over the
    first's ring) bit for bit as the volume alone, as band processes do."""
    alone = _passes(method, direction, None)
    layout = SharedFocusVolume.shared_layout(method=method, **VOLUME)
    with BandTaskThreads(3, layout, name="test-band") as pool:
        assert_same_blocks(alone, _passes(method, direction, pool))  # type: ignore[arg-type]
        assert pool.helpers_cpu_s() == 0.0  # counted with the process's own
    with pytest.raises(RuntimeError, match="used after they were closed"):
        pool.run_task("depth", {}, [(0, 1)])


@pytest.mark.parametrize("method", ["shape_select", "spc"])
def test_band_task_threads_measure_what_they_add(method: str) -> None:
    """The focus measure stage passing RawColumns to band task threads that measure their
    own rows gives the blocks of one band, bit for bit, both directions, for 2 and 4."""
    ref = _raw_blocks(method)
    assert sum(b.header.complete_columns for b in ref) > 200
    layout = SharedFocusVolume.shared_layout(**{**RAW_DEPTH, "method": method,
                                                "row_slack": 3, "col_slack": 3})
    for k in (2, 4):
        assert_same_depth_blocks(ref, _raw_blocks(method, BandTaskThreads(k, layout)))


def test_a_failing_band_task_thread_is_raised_by_the_wait_that_reaches_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A task that raises in a band thread is raised, once, by the first wait that reaches
    its ticket; one that raises in the caller's band is raised at once; a band that takes
    too long is named with its task and rows."""
    import threading

    from sffscan.stages import volume_tasks

    def fail_in_band_7(arrays: dict, params: dict, rows: tuple[int, int]) -> None:
        if rows[0] == 7:
            raise ArithmeticError(f"failed in rows {rows[0]}..{rows[1]}")

    release = threading.Event()
    monkeypatch.setitem(volume_tasks.TASKS, "fail7", fail_in_band_7)
    monkeypatch.setitem(volume_tasks.TASKS, "block",
                        lambda a, p, r: release.wait(5.0) if r[0] == 7 else None)
    layout = SharedFocusVolume.shared_layout(method="spc", **VOLUME)
    with BandTaskThreads(2, layout, timeout_s=0.2) as pool:
        ticket = pool.submit_task("fail7", {}, [(0, 7), (7, 9)])  # the caller's band passes
        with pytest.raises(ArithmeticError, match="failed in rows 7..9"):
            pool.wait_tasks(ticket)
        pool.wait_tasks()  # raised once
        with pytest.raises(ArithmeticError, match="failed in rows 7..7"):
            pool.submit_task("fail7", {}, [(7, 7), (0, 7)])
        with pytest.raises(ValueError, match="unknown band task 'nope'"):
            pool.run_task("nope", {}, [(0, 1), (1, 2)])
        with pytest.raises(ValueError, match="3 bands for 2 band workers"):
            pool.submit_task("depth", {}, [(0, 1), (1, 2), (2, 3)])
        try:
            pool.submit_task("block", {}, [(0, 0), (7, 9)])
            with pytest.raises(TimeoutError, match=r"band thread \(block, rows 7\.\.9\) took "
                               r"more than 0\.2 s"):
                pool.wait_tasks()
        finally:
            release.set()
