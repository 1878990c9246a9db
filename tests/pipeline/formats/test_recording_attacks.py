"""Recordings attacked (issue 23): chunk files swapped or copied (defect 7), a unique
recording id, array lengths claimed beyond the chunk files present and time stamps that go
back or jump by decades (defects 15, 16); property-based round trips of the metadata."""

from __future__ import annotations

import functools
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from hypothesis import example, given, settings
from hypothesis import strategies as st
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.completeness import FrameAccount
from sffscan.pipeline.formats.recording import (
    HEADER_COLUMNS,
    RecordingAttrs,
    header_row,
    read_recording_id,
)
from sffscan.pipeline.formats.recording_checks import Pacer, plausible_step_s
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame, FrameHeader

from tests.pipeline.formats.test_transport import tiny_config

N = 12


@functools.cache
def _simulated(n: int) -> tuple[Frame, ...]:
    return tuple(f for _, f in zip(range(n), simulate_frames(tiny_config()), strict=False))


def _write(path: Path, frames: list[Frame] | None = None) -> list[Frame]:
    cfg = tiny_config()
    if frames is None:
        frames = list(_simulated(N))
    writer = RecordingWriter(path, cfg, account=FrameAccount(planned=len(frames)))
    for f in frames:
        writer.write(f)
    writer.close()
    return frames


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rec = tmp_path_factory.mktemp("attacks") / "rec.zarr"
    _write(rec)
    return rec


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_a_new_recording_has_a_unique_id(recorded: Path, tmp_path: Path) -> None:
    other = tmp_path / "other.zarr"
    _write(other)
    a, b = read_recording_id(recorded), read_recording_id(other)
    assert a is not None and b is not None and a != b and len(a) == 32
    assert open_recording(recorded).recording_id == a
    assert zarr.open_group(str(recorded), mode="r").attrs["recording_id"] == a
    assert read_recording_id(tmp_path / "nothing.zarr") is None


@pytest.mark.parametrize("attack", ["swap", "copy", "swap-with-headers", "other-recording"])
def test_swapped_or_copied_chunk_files_are_found(recorded: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str],
                                                 attack: str) -> None:
    """Defect 7: every chunk's CRC is valid, the frames are not where they belong."""
    rec = _copy(recorded, tmp_path / "rec.zarr")
    f3, f5 = rec / "frames" / "c.3.0.0", rec / "frames" / "c.5.0.0"
    if attack.startswith("swap"):
        tmp = f3.read_bytes()
        f3.write_bytes(f5.read_bytes())
        f5.write_bytes(tmp)
        if attack == "swap-with-headers":  # the header copies go with their frames
            h3, h5 = rec / "headers" / "c.3.0", rec / "headers" / "c.5.0"
            tmp = h3.read_bytes()
            h3.write_bytes(h5.read_bytes())
            h5.write_bytes(tmp)
        hit = [3, 5]
    elif attack == "copy":
        shutil.copyfile(f3, f5)
        hit = [5]
    else:  # the same frame index of another recording of the same configuration
        other = tmp_path / "other.zarr"
        frames = list(_simulated(N))
        frames[5] = Frame(frames[5].header, frames[5].image ^ np.uint16(1))
        _write(other, frames)
        shutil.copyfile(other / "frames" / "c.5.0.0", f5)
        hit = [5]
    assert main(["info", str(rec), "--verify"]) == 3  # frames a replay leaves out
    out = capsys.readouterr().out
    assert "misplaced" in out and "frame index 5" in out, out
    assert "frames/c.5.0.0" in out or "headers/c.5.0" in out
    r = open_recording(rec)
    assert sorted(r.verify()) == hit
    # replay: those frames are left out (lost), the rest is replayed, the mosaic incomplete
    out_mosaic = tmp_path / "m.zarr"
    code = main(["replay", str(rec), "-o", str(out_mosaic), "-q"])
    assert code == 3
    attrs = zarr.open_group(str(out_mosaic), mode="r").attrs.asdict()
    assert attrs["frames_received"] == N - len(hit) and attrs["status"] == "incomplete"
    assert attrs["recording"]["misplaced"] == hit  # type: ignore[index,call-overload]


def test_an_intact_recording_replays_complete(recorded: Path, tmp_path: Path) -> None:
    assert main(["replay", str(recorded), "-o", str(tmp_path / "m.zarr"), "-q"]) == 0
    r = open_recording(recorded)
    assert r.verify() == [] and r.report.defects == 0 and not r.report.notes
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs.asdict()
    assert attrs["recording"]["identity"]["id"] == r.recording_id  # type: ignore[index,call-overload]


def _claim(rec: Path, entries: int) -> None:
    """Every array's zarr.json claims ``entries`` entries."""
    for meta in rec.glob("*/zarr.json"):
        doc = json.loads(meta.read_text())
        doc["shape"][0] = entries
        meta.write_text(json.dumps(doc))


@pytest.mark.parametrize("entries", [2**40, 10**8])
def test_claimed_lengths_are_checked_against_the_chunk_files(
        recorded: Path, tmp_path: Path, entries: int,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Defect 16: no MemoryError, no minutes: the entries past the chunk files hold nothing."""
    rec = _copy(recorded, tmp_path / "rec.zarr")
    _claim(rec, entries)
    r = open_recording(rec)
    assert r.report.claimed_entries == entries and r.report.frames == N
    assert r.report.defects == 1
    assert main(["info", str(rec)]) == 0
    assert f"claim {entries} entries" in capsys.readouterr().out
    assert main(["replay", str(rec), "-o", str(tmp_path / "m.zarr"), "-q"]) == 0
    assert main(["replay", str(rec), "-o", str(tmp_path / "s.zarr"), "-q", "--strict"]) == 2


def test_a_claimed_frame_count_past_the_files_is_bounded(recorded: Path,
                                                         tmp_path: Path) -> None:
    rec = _copy(recorded, tmp_path / "rec.zarr")
    zarr.open_group(str(rec), mode="r+").update_attributes({"frames": 2**40})
    r = open_recording(rec)
    assert r.report.claimed_entries == 2**40 and r.report.frames == N
    assert len(r.report.missing_metadata) <= 2048


def _with_timestamp(rec: Path, index: int, value: int) -> None:
    g = zarr.open_group(str(rec), mode="r+")
    g["timestamp_ns"][index] = value  # type: ignore[index]
    h = g["headers"]
    row = np.asarray(h[index])  # type: ignore[index]
    row[1] = value
    h[index] = row  # type: ignore[index]


def test_a_time_stamp_of_1e18_is_reported_and_never_slept(recorded: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """Defect 15: ``--realtime`` would sleep for decades; ``info`` saw no defect."""
    rec = _copy(recorded, tmp_path / "rec.zarr")
    _with_timestamp(rec, 6, 10**18)
    r = open_recording(rec)
    assert r.report.time_jumps == [6] and r.report.time_backwards == []  # a spike
    assert main(["info", str(rec)]) == 0
    out = capsys.readouterr().out
    assert "time jump   1: frame_id 6" in out
    slept: list[float] = []
    now = [0.0]

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    frames = list(r.frames(realtime=True, clock=lambda: now[0], sleep=sleep))
    assert len(frames) == N
    fps = r.config.optics.fps
    # never more than the plausible duration of the recorded scan (each step bounded)
    assert sum(slept) <= N * plausible_step_s(1, fps)
    assert sum(slept) == pytest.approx((N - 1) / fps, rel=0.05)


def test_backwards_time_stamps_are_named_as_such(recorded: Path, tmp_path: Path) -> None:
    rec = _copy(recorded, tmp_path / "rec.zarr")
    r0 = open_recording(rec)
    _with_timestamp(rec, 4, int(r0.meta["timestamp_ns"][2]))
    r = open_recording(rec)
    assert r.report.time_backwards == [4] and r.report.time_jumps == []
    assert any("time back  " in line and "4" in line for line in r.report.lines())


def test_the_pacer_replaces_implausible_steps_by_the_nominal_interval() -> None:
    now = [0.0]
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    p = Pacer(100.0, clock=lambda: now[0], sleep=sleep)
    for fid, ts in [(0, 0), (1, 10_000_000), (2, 10**18), (3, 10**18 + 10_000_000), (4, 5)]:
        p.wait(fid, ts)
    assert slept == pytest.approx([0.01] * 4)
    assert p.replaced == [2, 4]


def test_the_pacer_never_waits_past_the_plausible_scan_duration() -> None:
    """Each step just under the per-step bound: the whole still fits the span's bound."""
    now = [0.0]
    p = Pacer(100.0, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    step_ns = int(plausible_step_s(1, 100.0) * 0.99e9)
    for fid in range(50):
        p.wait(fid, fid * step_ns)
    assert p.replaced == []
    assert now[0] <= plausible_step_s(49, 100.0) + 1e-9


headers = st.builds(
    FrameHeader, frame_id=st.integers(0, 2**63 - 1), timestamp_ns=st.integers(0, 2**63 - 1),
    focus_index=st.integers(0, 2**31 - 1), pass_index=st.integers(0, 2**31 - 1),
    stage_x_um=st.none() | st.floats(allow_nan=False, allow_infinity=False),
    stage_y_um=st.none() | st.floats(allow_nan=False, allow_infinity=False))


@settings(max_examples=60, deadline=None)
@given(h=headers, index=st.integers(0, 2**40), digest=st.integers(0, 2**32 - 1))
def test_header_rows_hold_every_header_exactly(h: FrameHeader, index: int, digest: int) -> None:
    row = header_row(h, index=index, digest=digest)
    assert row.dtype == np.int64 and row.size == len(HEADER_COLUMNS)
    pos = row[3:5].view(np.float64)
    back = FrameHeader(frame_id=int(row[0]), timestamp_ns=int(row[1]),
                       focus_index=int(row[2]), pass_index=int(row[5]),
                       stage_x_um=None if np.isnan(pos[0]) else float(pos[0]),
                       stage_y_um=None if np.isnan(pos[1]) else float(pos[1]))
    assert back == h and int(row[6]) == index and int(row[7]) == digest


@settings(max_examples=60, deadline=None)
@given(data=st.fixed_dictionaries({
    "frame_shape": st.tuples(st.integers(-2, 2**40), st.integers(-2, 2**40)),
    "dtype": st.sampled_from(["uint8", "uint16", "float32", ""]),
    "format_version": st.integers(-1, 6),
    "recording_id": st.none() | st.text(max_size=40),
    "frames": st.none() | st.integers(-5, 2**64),
    "status": st.sampled_from(["recording", "complete", "failed", "done"]),
}))
def test_recording_attributes_are_validated_never_crash(data: dict[str, object]) -> None:
    """Any attribute values either validate (and round-trip through JSON) or raise pydantic's
    ValidationError, which the reader turns into a RecordingError naming the attribute."""
    from pydantic import ValidationError

    raw = {"format": "sffscan-recording", "scan_config": {}, **data}
    try:
        attrs = RecordingAttrs.model_validate(raw)
    except ValidationError:
        return
    assert attrs.recording_id is None or len(attrs.recording_id) == 32
    assert RecordingAttrs.model_validate_json(attrs.model_dump_json()) == attrs


def test_a_backwards_time_stamp_is_named_not_a_backwards_stage(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Defect 15: frames placed by the speed model (no stage position) with a time stamp that
    goes back stopped the replay as 'stage_x_um moves -x'. Now the frame is named, left out
    (lost) and the replay is incomplete."""
    frames = [Frame(f.header.model_copy(update={"stage_x_um": None, "stage_y_um": None}),
                    f.image)
              for f in _simulated(30)]
    frames[10] = Frame(frames[10].header.model_copy(
        update={"timestamp_ns": frames[2].header.timestamp_ns}), frames[10].image)
    rec = tmp_path / "rec.zarr"
    _write(rec, frames)
    r = open_recording(rec)
    assert r.report.time_backwards == [10] and r.report.time_left_out == [10]
    assert r.report.frames == 29
    with caplog.at_level(logging.WARNING):
        code = main(["replay", str(rec), "-o", str(tmp_path / "m.zarr"), "-q"])
    assert code == 3
    assert "time back   1: frame_id 10" in caplog.text
    assert "moves" not in caplog.text
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs.asdict()
    assert attrs["frames_received"] == 29 and attrs["status"] == "incomplete"


@settings(max_examples=12, deadline=None)
# found by hypothesis on 2026-12-05: a lost entry rebuilt from a header copy whose column 5
# of 8 (the pass index) held a value no int32 column holds raised OverflowError
@example(edits=[("frame_id", 0, -1), ("headers", 0, 3_525_100_189)])
@given(edits=st.lists(st.tuples(
    st.sampled_from(["frame_id", "timestamp_ns", "focus_index", "pass_index", "headers"]),
    st.integers(0, N - 1), st.integers(-2**63, 2**63 - 1)), min_size=1, max_size=4))
def test_any_metadata_values_are_reported_never_crash(recorded: Path, edits: list[
        tuple[str, int, int]]) -> None:
    """Arbitrary values written into the per-frame metadata and the header copies: the
    reader reports (or refuses with RecordingError), replays only valid headers, never
    raises anything else."""
    import tempfile

    from sffscan.pipeline.formats.recording import RecordingError

    with tempfile.TemporaryDirectory() as tmp:
        rec = _copy(recorded, Path(tmp) / "rec.zarr")
        g = zarr.open_group(str(rec), mode="r+")
        for name, index, value in edits:
            arr = g[name]
            if name == "headers":
                row = np.asarray(arr[index])  # type: ignore[index]
                row[value % 8] = value
                arr[index] = row  # type: ignore[index]
            else:
                info = np.iinfo(arr.dtype)  # type: ignore[union-attr]
                arr[index] = min(max(value, info.min), info.max)  # type: ignore[index]
        try:
            r = open_recording(rec)
        except RecordingError:
            return
        r.verify()
        got = [f.header for f in r.frames()]
        assert len(got) == r.report.frames
        assert all(a.frame_id < b.frame_id for a, b in zip(got, got[1:], strict=False))
