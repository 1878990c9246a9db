"""Camera source (sffscan.pipeline.hardware.camera_source): real acquisition from the GenTL
producer shipped in
the genicam wheel (viky.cti: continuous mode only, no trigger, no time stamps), and the
frame_id / focus-level / time-stamp rules against a fake camera."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.config import ConfigError, ScanConfig, config_from_dict
from sffscan.pipeline.hardware.camera_source import (
    CameraError,
    CameraStats,
    FrameIdUnwrapper,
    RawImage,
    camera_frames,
    find_cti,
)
from sffscan.pipeline.hardware.daq import SimDaq
from sffscan.pipeline.plan import frame_count
from sffscan.pipeline.runtime import StageFailed
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.messages import Frame


def viky_cti() -> Path:
    import genicam

    path = Path(genicam.__file__).parent / "viky.cti"
    if not path.is_file():
        pytest.fail(f"viky.cti not found in the genicam wheel at {path}")
    return path


def viky_config(**camera: Any) -> ScanConfig:
    """A small region at viky's top rate: 160 x 100 px of 17 µm, 200 fps, N = 10, 20 mm/s
    (5.9 px a frame) over a 24 mm strip: 255 frames; 64 buffers absorb a slow start."""
    return config_from_dict({
        "source": {"kind": "camera"},
        "optics": {"width_px": 160, "height_px": 100, "pixel_um": 17.0, "n_levels": 10,
                   "fps": 200.0, "bit_depth": 8},
        "motion": {"speed_mm_s": 20.0, "x_start_mm": 0.0, "x_end_mm": 24.0},
        "processing": {"block_columns": 64, "registration": False},
        "output": {"chunk_px": 64},
        "camera": {"cti": str(viky_cti()), "pixel_format": "Mono8", "num_buffers": 64,
                   **camera},
    }, origin="test")


def test_viky_200_frames_through_the_whole_pipeline(tmp_path: Path) -> None:
    cfg = viky_config()
    n = frame_count(cfg)
    assert n >= 200
    st = CameraStats()
    report = run_scan(cfg, frames=camera_frames(cfg, stats=st), output=tmp_path / "m.zarr",
                      progress=False)
    assert report.frames == st.frames >= 200
    by_stage = {s.name: s.frames for s in report.result.stages}
    assert by_stage["focus_measure"] == by_stage["depth"] == st.frames  # the whole pipeline
    assert st.frames + st.lost == n  # every planned frame_id arrived or is counted lost
    # viky has no time stamps and no trigger: the host-clock fallback is marked, and the
    # missing trigger nodes are named
    assert st.timestamps == "host clock" and st.frame_ids == "device"
    assert any("TriggerMode" in note for note in st.notes)
    assert st.underruns is not None  # read from the producer (GenTL NUM_UNDERRUN)
    # the source stage saw the same gaps the camera counted
    assert report.result.extras["source"]["frames_lost"] == st.lost
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    assert g.attrs["status"] == "complete"
    assert report.result.extras["mosaic"]["valid_pixels"] > 0
    assert report.result.extras["depth"]["complete_columns"] > 0


def test_viky_images_are_copied_once_into_the_arrays_the_runtime_binds(
        tmp_path: Path) -> None:
    """camera_frames offers its FrameBuffers: bound to an allocator (what the process
    placement binds: its frame ring's slots), each image is copied out of the producer's
    buffer into an array from it, the array the frame carries; the scan in processes, where
    that is the ring, takes every frame through the pipeline."""
    cfg = viky_config()
    frames = camera_frames(cfg)
    handed: list[np.ndarray] = []

    def alloc(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        handed.append(np.zeros(shape, dtype))
        return handed[-1]

    frames.buffers.bind(alloc)
    try:
        got = [next(frames) for _ in range(30)]
    finally:
        frames.close()
    assert len(handed) >= 30
    assert all(any(f.image is a for a in handed) for f in got)
    assert all(f.image.shape == (100, 160) and f.image.dtype == np.uint8 for f in got)
    assert sum(int(f.image.max()) > 0 for f in got) >= 25  # viky's pattern, copied in
    pcfg = viky_config().model_copy(update={"processing": viky_config().processing.model_copy(
        update={"execution": "processes"})})
    st = CameraStats()
    report = run_scan(pcfg, frames=camera_frames(pcfg, stats=st),
                      output=tmp_path / "p.zarr", progress=False)
    assert "processes" in report.result.extras
    assert report.frames == st.frames >= 200
    assert {s.name: s.frames for s in report.result.stages}["depth"] == st.frames


def test_viky_lost_frames_are_counted_and_marked(tmp_path: Path) -> None:
    """A consumer that stalls for 0.3 s (60 frames at 200 fps, 8 buffers) loses frames:
    the gap shows in frame_id, the source counts it and the focus volume invalidates the
    columns that missed levels. The camera also counts planned frames lost after the last
    one it delivered (the first frame_id past the plan shows them), which the source
    stage, seeing no frame after them, cannot: on a loaded machine the camera's
    count was one gap more than the source's (fresh-clone run, 2-core VM)."""
    cfg = viky_config(num_buffers=8)
    st = CameraStats()
    ids: list[int] = []

    def stalling(frames: Iterator[Frame]) -> Iterator[Frame]:
        try:
            for frame in frames:
                if frame.header.frame_id == 60:
                    time.sleep(0.3)
                ids.append(frame.header.frame_id)
                yield frame
        finally:
            getattr(frames, "close")()  # noqa: B009 - a generator's close

    report = run_scan(cfg, frames=stalling(camera_frames(cfg, stats=st)),
                      output=tmp_path / "m.zarr", progress=False)
    extras = report.result.extras
    assert st.gaps >= 1 and st.lost >= 10
    tail = frame_count(cfg) - 1 - ids[-1]  # planned frames lost after the last one
    assert extras["source"]["frame_id_gaps"] == st.gaps - (tail > 0)
    assert extras["source"]["frames_lost"] == st.lost - tail
    assert extras["depth"]["incomplete_columns"] > 0
    assert zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs["status"] == "complete"


def test_viky_pixel_format_that_does_not_match_is_refused() -> None:
    cfg = viky_config(pixel_format=None)  # viky's default RGBa8
    gen = camera_frames(cfg)
    with pytest.raises(CameraError, match="RGBa8 is not supported"):
        next(gen)


def test_viky_region_outside_the_device_limits() -> None:
    cfg = config_from_dict({**viky_config().model_dump(),
                            "optics": {**viky_config().optics.model_dump(), "height_px": 64}})
    with pytest.raises(CameraError, match="Height must lie in 100..800"):
        next(camera_frames(cfg))


# --- fake camera --------------------------------------------------------------------------


class FakeCamera:
    """Serves images with the given device frame counters and time stamps."""

    def __init__(self, ids: Sequence[int | None], ts: Sequence[int | None] | None = None,
                 *, underruns: int | None = 0, shape: tuple[int, int] = (100, 160)) -> None:
        self.ids = ids
        self.ts = ts if ts is not None else [None] * len(ids)
        self.n_under = underruns
        self.shape = shape
        self.calls: list[str] = []
        self.outs: list[np.ndarray | None] = []  # the arrays offered to fetch
        self.k = 0

    def configure(self, cfg: ScanConfig) -> list[str]:
        self.calls.append("configure")
        return ["device lacks nodes: ExposureTime"]

    def start(self) -> None:
        self.calls.append("start")

    def fetch(self, timeout_s: float, *, out: np.ndarray | None = None) -> RawImage:
        self.outs.append(out)
        if self.k >= len(self.ids):
            raise CameraError(f"no frame within camera.fetch_timeout_s = {timeout_s:g} s")
        img = np.full(self.shape, self.k % 256, np.uint8)
        raw = RawImage(img, self.ids[self.k], self.ts[self.k])
        self.k += 1
        return raw

    def underruns(self) -> int | None:
        return self.n_under

    def stop(self) -> None:
        self.calls.append("stop")

    def close(self) -> None:
        self.calls.append("close")


class OrderDaq(SimDaq):
    def __init__(self, cam: FakeCamera) -> None:
        super().__init__()
        self.cam = cam

    def start(self, waveform: Any) -> None:
        assert self.cam.calls[-1] == "start", "the DAQ must start after the camera is armed"
        super().start(waveform)


def test_frame_id_wraps_around_and_gaps_are_lost_frames() -> None:
    u = FrameIdUnwrapper(65536)
    ids = [u(r) for r in (65533, 65534, 65535, 0, 1, 4, 5)]
    assert ids == [0, 1, 2, 3, 4, 7, 8]
    assert (u.gaps, u.lost) == (1, 2)
    with pytest.raises(CameraError, match="went from 5 to 5"):
        u(5)
    never_wraps = FrameIdUnwrapper(0)
    never_wraps(10)
    with pytest.raises(CameraError, match="frame_id_modulus"):
        never_wraps(9)


def test_fake_camera_headers_follow_the_rules() -> None:
    cfg = viky_config(frames=12, frame_id_modulus=65536, focus_phase=3)
    ids = [65530 + k for k in range(6)] + [0, 1, 2, 5, 6, 7, 8]  # wrap, then a gap of 2
    ts = [1_000_000 + 5_000_000 * k for k in range(len(ids))]
    cam = FakeCamera(ids, ts, underruns=2)
    daq = OrderDaq(cam)
    st = CameraStats()
    frames = list(camera_frames(cfg, camera=cam, daq=daq, stats=st))
    fids = [f.header.frame_id for f in frames]
    assert fids == [0, 1, 2, 3, 4, 5, 6, 7, 8, 11]  # 12 reached at the next frame: stop
    assert [f.header.focus_index for f in frames] == [(k + 3) % 10 for k in fids]
    assert [f.header.timestamp_ns for f in frames] == [5_000_000 * k for k in range(10)]
    assert (st.frames, st.gaps, st.lost, st.underruns) == (10, 1, 2, 2)
    assert st.timestamps == "device"
    assert "buffer underruns 2" in st.summary()
    assert cam.calls == ["configure", "start", "stop", "close"]
    # every fetch was offered an array of the configured frame for the image
    assert len(cam.outs) == cam.k == 11 and all(
        o is not None and o.shape == (100, 160) and o.dtype == np.uint8 for o in cam.outs)
    assert daq.calls == ["start", "stop", "close"]


def test_device_released_when_the_consumer_stops_early_or_fails() -> None:
    cfg = viky_config(frames=50)
    cam = FakeCamera(list(range(1, 60)))
    daq = SimDaq()
    gen = camera_frames(cfg, camera=cam, daq=daq)
    next(gen)
    gen.close()  # type: ignore[attr-defined]
    assert cam.calls[-2:] == ["stop", "close"] and daq.calls == ["start", "stop", "close"]

    cam = FakeCamera([1, 2, 3])  # then times out
    with pytest.raises(CameraError, match="no frame within"):
        list(camera_frames(cfg, camera=cam, daq=SimDaq()))
    assert cam.calls[-2:] == ["stop", "close"]


def test_no_device_counter_counts_fetched_frames() -> None:
    cfg = viky_config(frames=4)
    st = CameraStats()
    frames = list(camera_frames(cfg, camera=FakeCamera([None] * 5), daq=SimDaq(), stats=st))
    assert [f.header.frame_id for f in frames] == [0, 1, 2, 3]
    assert st.frame_ids == "host count" and st.timestamps == "host clock"
    ts = [f.header.timestamp_ns for f in frames]
    assert ts[0] == 0 and ts == sorted(ts)


def test_a_camera_source_failure_stops_the_scan_naming_the_source(tmp_path: Path) -> None:
    cfg = viky_config(frames=30)
    cam = FakeCamera([1, 2, 3, 3])  # the counter stands still
    with pytest.raises(StageFailed, match="source.*went from 3 to 3"):
        run_scan(cfg, frames=camera_frames(cfg, camera=cam, daq=SimDaq()),
                 output=tmp_path / "m.zarr", progress=False)
    assert cam.calls[-2:] == ["stop", "close"]


def test_find_cti(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    base = viky_config().model_dump()
    base["camera"]["cti"] = None
    cfg = config_from_dict(base)
    monkeypatch.delenv("SFFSCAN_CTI", raising=False)
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(viky_cti().parent))
    assert find_cti(cfg) == viky_cti()
    monkeypatch.setenv("SFFSCAN_CTI", str(tmp_path / "none.cti"))
    with pytest.raises(ConfigError, match=r"\$SFFSCAN_CTI: GenTL producer .*none.cti not found"):
        find_cti(cfg)
    monkeypatch.delenv("SFFSCAN_CTI")
    monkeypatch.delenv("GENICAM_GENTL64_PATH")
    with pytest.raises(ConfigError, match="no GenTL producer given"):
        find_cti(cfg)


# --- review: defects found and fixed ------------------------------------------------------


def test_frames_lost_at_the_end_of_the_scan_are_counted() -> None:
    """The plan wants 12 frames; device counters 11 and 12 (frame_id 10, 11) never arrive,
    the next frame (frame_id 13) ends the scan: 2 frames lost, not 0."""
    cfg = viky_config(frames=12)
    st = CameraStats()
    frames = list(camera_frames(cfg, camera=FakeCamera(list(range(1, 11)) + [14, 15]),
                                daq=SimDaq(), stats=st))
    assert [f.header.frame_id for f in frames] == list(range(10))
    assert (st.frames, st.gaps, st.lost) == (10, 1, 2)
    assert st.frames + st.lost == 12
    assert "2 lost in 1 frame_id gaps" in st.summary()


def test_frames_lost_at_the_end_reach_the_source_stage() -> None:
    """No later frame_id shows those 2 frames' gap to the source stage; the camera tells it
    (``SourceFrames.lost_at_end``), so the scan's report counts them as the camera does
    (a viky scan on a loaded machine lost 38 frames this way and reported 0)."""
    from sffscan.stages.frame_source import SourceStage

    cfg = viky_config(frames=12)
    st = CameraStats()
    src = SourceStage(camera_frames(cfg, camera=FakeCamera(list(range(1, 11)) + [14, 15]),
                                    daq=SimDaq(), stats=st),
                      shape=(100, 160), dtype="uint8", n_levels=10, max_value=255, passes=1,
                      area_um=(0.0, 0.0, 1e9, 1e9))
    assert [f.header.frame_id for f in src.produce()] == list(range(10))
    assert src.extra_stats() == {"frame_id_gaps": 1, "frames_lost": 2}
    assert (st.gaps, st.lost, st.lost_at_end) == (1, 2, 2)
    # a gap inside the stream and none at the end: the stage's own count, nothing added
    st = CameraStats()
    src = SourceStage(camera_frames(cfg, camera=FakeCamera([1, 2, 5, 6, 7, 8, 9, 10, 11, 12,
                                                            13]),
                                    daq=SimDaq(), stats=st),
                      shape=(100, 160), dtype="uint8", n_levels=10, max_value=255, passes=1,
                      area_um=(0.0, 0.0, 1e9, 1e9))
    assert len(list(src.produce())) == 10
    assert src.extra_stats() == {"frame_id_gaps": 1, "frames_lost": 2}
    assert (st.gaps, st.lost, st.lost_at_end) == (1, 2, 0)


def test_an_exposure_longer_than_half_a_step_is_refused_before_anything_starts() -> None:
    """The trigger sits at the step's centre: an exposure past 1 / (2 fps) (2500 µs at
    200 fps) runs into the lens's next step, mixing two focus levels in one frame."""
    from sffscan.pipeline.hardware.camera_source import check_exposure

    cfg = viky_config(frames=5, exposure_us=3000.0)
    cam = FakeCamera(list(range(1, 10)))
    daq = SimDaq()
    with pytest.raises(CameraError, match=r"camera.exposure_us = 3000 µs.*2500 µs"):
        list(camera_frames(cfg, camera=cam, daq=daq))
    assert "start" not in cam.calls and daq.calls == [] and cam.calls[-1] == "close"
    # pixel scale / speed: 17 µm at 20 mm/s = 850 µs; longer smears: said, not refused
    notes = check_exposure(viky_config(), 1000.0, origin="camera.exposure_us")
    assert len(notes) == 1 and "smear" in notes[0] and "850 µs" in notes[0]
    assert check_exposure(viky_config(), 800.0, origin="camera.exposure_us") == []
    # free-run (no trigger): no staircase step to stay inside
    assert check_exposure(viky_config(trigger=False), 3000.0, origin="x") != []


def test_real_daq_with_an_untriggered_camera_is_refused() -> None:
    """viky has no trigger nodes: with daq.kind = 'nidaqmx' its frames would not be
    synchronised with the lens staircase; refused (the device released), never a scan
    with focus levels guessed from the frame count."""
    base = viky_config().model_dump()
    base["daq"]["kind"] = "nidaqmx"
    cfg = config_from_dict(base)
    with pytest.raises(CameraError, match="not hardware-triggered.*TriggerMode.*daq.kind"):
        next(camera_frames(cfg))
    # the device was released: it can be opened again at once
    st = CameraStats()
    assert len(list(camera_frames(viky_config(frames=3), stats=st))) == 3
