"""Replay: bit for bit with the live run, overrides recorded, other writers' recordings,
lost frames marked invalid, real-time pacing, ``sffscan info``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.mosaic.layout import ARRAYS

from tests.pipeline.formats.test_recording import plain_recording
from tests.scan_helpers import small_config


def _attrs(path: Path) -> dict[str, Any]:
    return zarr.open_group(str(path), mode="r").attrs.asdict()


def _arrays(path: Path) -> dict[str, np.ndarray]:
    g = zarr.open_group(str(path), mode="r")
    return {n: np.asarray(g[n]) for n in ARRAYS}


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A live scan (registration on, wobble) recorded with --record: (recording, mosaic)."""
    d = tmp_path_factory.mktemp("live")
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0, "wobble_along_px": 1.0,
                               "wobble_across_px": 1.0})
    (d / "scan.toml").write_text(config_to_toml(cfg))
    rec, mosaic = d / "rec.zarr", d / "live.zarr"
    assert main(["scan", "--config", str(d / "scan.toml"), "-o", str(mosaic), "--record",
                 str(rec), "-q", "--no-evaluate"]) == 0
    return rec, mosaic


def test_replay_reproduces_the_live_mosaic_bit_for_bit(live: tuple[Path, Path],
                                                       tmp_path: Path) -> None:
    rec, mosaic = live
    out = tmp_path / "replay.zarr"
    assert main(["replay", str(rec), "-o", str(out), "-q"]) == 0
    want, got = _arrays(mosaic), _arrays(out)
    assert np.isfinite(want["height"]).sum() > 50_000
    for name in ARRAYS:
        assert np.array_equal(got[name], want[name], equal_nan=True), name
    attrs = _attrs(out)
    assert attrs["status"] == "complete"
    assert attrs["recording"]["frames"] == open_recording(rec).report.frames
    assert attrs["processing"] == _attrs(mosaic)["processing"]


def test_frames_are_decoded_into_the_arrays_the_runtime_binds(live: tuple[Path, Path]) -> None:
    """A recording's frames iterator offers its FrameBuffers: bound to an allocator (what
    the process placement binds: its frame ring's slots), every frame is decoded into an
    array from it, the values those of the unbound read."""
    rec, _ = live
    want = [f.image for f in open_recording(rec).frames()]
    frames = open_recording(rec).frames()
    handed: list[np.ndarray] = []

    def alloc(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        handed.append(np.full(shape, 12345, dtype))
        return handed[-1]

    frames.buffers.bind(alloc)
    got = list(frames)
    assert len(got) == len(want) == len(handed) > 100
    for f, a, w in zip(got, handed, want, strict=True):
        assert f.image is a
        np.testing.assert_array_equal(f.image, w)


def test_replay_in_processes_equals_threads_with_corrupt_frames(live: tuple[Path, Path],
                                                               tmp_path: Path) -> None:
    """Replayed in processes (frames decoded straight into the frame ring's slots) the
    mosaic is the thread placement's bit for bit, also when two frames in three fail their
    checksum: each is left out as lost, and the slot it was decoded into is given back (77
    slots kept would leave too few of the ring's for the scan to finish)."""
    import shutil

    rec, mosaic = live
    bad = tmp_path / "bad.zarr"
    shutil.copytree(rec, bad)
    chunks = sorted((bad / "frames").glob("c.*"), key=lambda p: int(p.name.split(".")[1]))
    assert len(chunks) == 116
    for p in chunks:
        if int(p.name.split(".")[1]) % 3:
            raw = bytearray(p.read_bytes())
            raw[len(raw) // 2] ^= 0x01
            p.write_bytes(bytes(raw))
    outs = {}
    for mode in ("threads", "processes"):
        out = tmp_path / f"{mode}.zarr"
        assert main(["replay", str(rec), "-o", str(out), "-q", "--execution", mode]) == 0
        outs[mode] = _arrays(out)
        corrupt = tmp_path / f"bad-{mode}.zarr"
        assert main(["replay", str(bad), "-o", str(corrupt), "-q", "--execution", mode]) == 3
        outs[f"bad-{mode}"] = _arrays(corrupt)
        assert _attrs(corrupt)["frames_received"] == 39
    want = _arrays(mosaic)
    for name in ARRAYS:
        assert np.array_equal(outs["processes"][name], want[name], equal_nan=True), name
        assert np.array_equal(outs["bad-processes"][name], outs["bad-threads"][name],
                              equal_nan=True), name


def test_overrides_are_applied_and_recorded(live: tuple[Path, Path], tmp_path: Path) -> None:
    rec, mosaic = live
    out = tmp_path / "tenv.zarr"
    assert main(["replay", str(rec), "-o", str(out), "-q", "--operator", "tenv", "--window",
                 "7", "--method", "argmax", "--no-registration"]) == 0
    p = _attrs(out)["processing"]
    assert p["focus_operator"] == "tenv" and p["window"] == 7
    assert p["depth_method"] == "argmax" and p["registration"] is False
    assert not np.array_equal(_arrays(out)["height"], _arrays(mosaic)["height"], equal_nan=True)
    # the recording is evidence: replay never changes it
    assert open_recording(rec).config.processing.focus_operator == "glvm"


def test_a_recording_written_with_plain_zarr_calls_replays(live: tuple[Path, Path],
                                                           tmp_path: Path) -> None:
    rec, mosaic = live
    r = open_recording(rec)
    plain = tmp_path / "plain.zarr"
    plain_recording(plain, r.config, list(r.frames()))
    out = tmp_path / "plain-replay.zarr"
    assert main(["replay", str(plain), "-o", str(out), "-q"]) == 0
    for name, want in _arrays(mosaic).items():
        assert np.array_equal(_arrays(out)[name], want, equal_nan=True), name


def test_lost_frames_leave_invalid_columns_never_filled(live: tuple[Path, Path], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    rec, mosaic = live
    r = open_recording(rec)
    # 20 frames lost: more than a column's frames in view beyond the N it needs (66-70 for
    # this geometry), so the columns in view meanwhile surely miss levels (8 lost frames
    # touched only a few edge columns, or none, as registration moved them by a pixel)
    frames = [f for f in r.frames() if not 50 <= f.header.frame_id < 70]
    gappy = tmp_path / "gappy.zarr"
    plain_recording(gappy, r.config, frames)
    out = tmp_path / "gappy-replay.zarr"
    # 20 of the planned frames never arrive: the mosaic is 'incomplete', exit 3 (issue 13)
    assert main(["replay", str(gappy), "-o", str(out), "-q"]) == 3
    text = capsys.readouterr()
    assert _attrs(out)["status"] == "incomplete"
    assert (_attrs(out)["frames_expected"], _attrs(out)["frames_received"]) == (116, 96)
    assert "gaps        1 (20 frames lost): 50..69" in text.err
    assert "frame_id_gaps 1, frames_lost 20" in text.out
    got, want = _arrays(out), _arrays(mosaic)
    lost = np.isnan(got["height"]) & np.isfinite(want["height"])
    assert lost.sum() > 500  # columns that missed levels are invalid ...
    assert (got["confidence"][np.isnan(got["height"])] == 0).all()  # ... and not filled
    rec_attr = _attrs(out)["recording"]
    assert rec_attr["frames_lost"] == 20 and rec_attr["gaps"] == [[50, 20]]
    assert main(["replay", str(gappy), "-o", str(tmp_path / "strict.zarr"), "-q",
                 "--strict"]) == 2


def test_realtime_paces_frames_by_their_time_stamps(live: tuple[Path, Path]) -> None:
    rec, _ = live
    r = open_recording(rec)
    now = [100.0]
    sleeps: list[float] = []

    def sleep(dt: float) -> None:
        sleeps.append(dt)
        now[0] += dt

    frames = r.frames(realtime=True, clock=lambda: now[0], sleep=sleep)
    ts = [f.header.timestamp_ns for _, f in zip(range(20), frames, strict=False)]
    assert len(sleeps) == 19
    assert sum(sleeps) == pytest.approx((ts[-1] - ts[0]) * 1e-9, abs=1e-9)
    assert sleeps[0] == pytest.approx(1 / 150, rel=1e-3)


def test_info_summarises_a_recording_and_refuses_what_is_not_one(
        live: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rec, mosaic = live
    n = open_recording(rec).report.frames
    assert main(["info", str(rec), "--verify"]) == 0
    out = capsys.readouterr().out
    assert f"frames      {n} usable of {n} entries" in out
    assert "150.0 frames/s" in out and "codec blosc-lz4" in out and "0 corrupt" in out
    assert main(["info", str(mosaic)]) == 0
    assert "tiles" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "nothing.zarr")]) == 2
    assert main(["replay", str(mosaic), "-o", str(tmp_path / "x.zarr")]) == 2
    assert "not an sffscan recording" in capsys.readouterr().err


def test_info_on_a_mosaic_with_invalid_attributes_names_the_attribute(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "bad.zarr"
    g = zarr.open_group(str(bad), mode="w")
    g.attrs.update({"format": "sffscan-mosaic", "status": "weird"})
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.zarr" in err and "attribute 'status'" in err


def test_replay_places_the_frames_by_the_printers_motion_queue(live: tuple[Path, Path],
                                                               tmp_path: Path) -> None:
    """Format 5: the motion queue stored with the recording gives every frame's stage
    position. A queue that reproduces the headers replays the live mosaic; one whose stage
    origin is 4 px off moves the whole mosaic by 4 px (the queue wins)."""
    import shutil

    from sffscan.pipeline.formats.recording_motion import add_motion_queue, motion_queue_for

    from tests.pipeline.formats.test_recording_motion import queue_of_headers

    rec, mosaic = live
    px = open_recording(rec).config.optics.pixel_um
    want = _arrays(mosaic)
    for dx_px in (0, 4):
        copy = tmp_path / f"rec{dx_px}.zarr"
        shutil.copytree(rec, copy)
        seg, clock = queue_of_headers(copy)
        add_motion_queue(copy, seg, motion_queue_for(
            seg, clock=clock, stage_origin_mm=(-dx_px * px / 1000.0, 0.0)))
        out = tmp_path / f"replay{dx_px}.zarr"
        assert main(["replay", str(copy), "-o", str(out), "-q"]) == 0
        got = _arrays(out)
        h, w = got["height"], want["height"]
        cols = np.flatnonzero(np.isfinite(w).any(axis=0))
        a, b = cols[0] + 8, cols[-1] - 8  # away from the mosaic's ends
        np.testing.assert_array_equal(h[:, a + dx_px:b + dx_px], w[:, a:b])
