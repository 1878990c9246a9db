"""The printer's motion queue (Klipper's ``motion_report/dump_trapq``) with a recording:
exact positions from constant-acceleration segments, coverage refused clearly, storage as
format version 5, the reader placing frames by it."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.formats.recording import FrameClock, RecordingError
from sffscan.pipeline.formats.recording_motion import (
    MotionQueueError,
    add_motion_queue,
    motion_queue_for,
    segments_from_dump,
    trapq_positions,
    trigger_print_time,
)
from sffscan.pipeline.formats.recording_reader import open_recording

from tests.scan_helpers import small_config

# one trapezoidal move of 10 mm along (0.6, 0.8): 0 -> 15 mm/s at 1000 mm/s² (15 ms,
# 0.1125 mm), cruise 9.775 mm (0.651667 s), 15 -> 0 mm/s (15 ms); a null segment before
T0, TA = 10.0, 0.015
DA = 0.5 * 1000 * TA**2
TC = (10.0 - 2 * DA) / 15.0
D = (0.6, 0.8, 0.0)
ROWS = [
    [T0 - 1.0, 1.0, 0.0, 0.0, [5.0, 5.0, 0.2], [0.0, 0.0, 0.0]],
    [T0, TA, 0.0, 1000.0, [5.0, 5.0, 0.2], list(D)],
    [T0 + TA, TC, 15.0, 0.0, [5.0 + 0.6 * DA, 5.0 + 0.8 * DA, 0.2], list(D)],
    [T0 + TA + TC, TA, 15.0, -1000.0, [5.0 + 0.6 * (10 - DA), 5.0 + 0.8 * (10 - DA), 0.2],
     list(D)],
]
END = T0 + 2 * TA + TC


def test_positions_are_the_constant_acceleration_kinematics() -> None:
    seg = segments_from_dump(ROWS[::-1] + ROWS[1:2])  # any order, a repeated row dropped
    assert seg.shape == (4, 10) and np.all(np.diff(seg[:, 0]) > 0)
    t = np.array([T0 - 0.5, T0, T0 + 0.01, T0 + TA + 0.2, END - 0.005, END])
    s = np.array([0.0, 0.0, 0.5 * 1000 * 0.01**2, DA + 15 * 0.2,
                  10.0 - 0.5 * 1000 * 0.005**2, 10.0])  # path length along D, mm
    want = np.array([5.0, 5.0, 0.2]) + s[:, None] * np.array(D)
    got = trapq_positions(seg, t)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # continuous at every boundary: the end of one segment is the start of the next
    for k in range(1, 4):
        a = trapq_positions(seg[k - 1:k], [seg[k, 0]])
        np.testing.assert_allclose(a[0], seg[k, 4:7], atol=1e-12)


@pytest.mark.parametrize(("t", "what"), [(T0 - 1.5, "not covered"), (END + 0.01, "not covered")])
def test_a_time_outside_the_queue_is_refused(t: float, what: str) -> None:
    seg = segments_from_dump(ROWS)
    with pytest.raises(MotionQueueError, match=rf"time {t:.6f} s \(entry 1,.*{what}") as e:
        trapq_positions(seg, [T0, t])
    assert e.value.entry == 1


def test_a_gap_between_segments_is_refused_and_named() -> None:
    seg = segments_from_dump([ROWS[0], ROWS[1], ROWS[3]])  # the cruise is missing
    with pytest.raises(MotionQueueError, match="in a gap between segments"):
        trapq_positions(seg, [T0 + 0.3])
    assert trapq_positions(seg, [T0 + TA])[0, 0] == pytest.approx(5.0 + 0.6 * DA)


@pytest.mark.parametrize(("rows", "match"), [
    ([[1.0, 1.0, 0.0, 0.0, [0, 0, 0]]], r"row 0 is .*expected \[time, duration"),
    ([[1.0, 1.0, 0.0, 0.0, [0, 0], [1, 0, 0]]], "row 0 is"),
    ([[1.0, -1.0, 0.0, 0.0, [0, 0, 0], [1, 0, 0]]], "negative duration"),
    ([[1.0, 1.0, 0.0, 0.0, [0, 0, float("nan")], [1, 0, 0]]], "not finite"),
    ([[1.0, 1.0, 0.0, 0.0, [0, 0, 0], [1, 1, 0]]], "longer than 1"),
    ([[1.0, 1.0, 0.0, 0.0, [0, 0, 0], [1, 0, 0]], [1.5, 1.0, 0.0, 0.0, [0, 0, 0], [1, 0, 0]]],
     "rows 0 and 1 overlap"),
    ([], "no segment"),
])
def test_malformed_dump_rows_are_named(rows: list[object], match: str) -> None:
    with pytest.raises(MotionQueueError, match=match):
        segments_from_dump(rows, where="dump")  # type: ignore[arg-type]


def test_the_trigger_is_the_first_move_from_the_raster_start_after_a_standstill() -> None:
    seg = segments_from_dump(ROWS)
    assert trigger_print_time(seg, (5.0, 5.0)) == T0
    with pytest.raises(MotionQueueError, match="raster's start is not in the queue"):
        trigger_print_time(seg, (5.0, 5.0), after_s=T0 + 0.001)


# --- stored with a recording ---------------------------------------------------------


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return recorded_scan(tmp_path_factory.mktemp("motion"), x_end_mm=4.0)


def recorded_scan(folder: Path, *, x_end_mm: float) -> Path:
    """``sffscan scan --record`` of the small test scan from x = 2 mm to ``x_end_mm``
    (registration off), in ``folder``; returns the recording."""
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": x_end_mm},
                       processing={"registration": False})
    (folder / "scan.toml").write_text(config_to_toml(cfg))
    rec = folder / "rec.zarr"
    assert main(["scan", "--config", str(folder / "scan.toml"), "-o",
                 str(folder / "live.zarr"), "--record", str(rec), "-q",
                 "--no-evaluate"]) == 0
    return rec


def queue_of_headers(rec: Path, *, origin_mm: tuple[float, float] = (0.0, 0.0),
                     t0_s: float = 100.0) -> tuple[np.ndarray, FrameClock]:
    """Segments that reproduce the recorded stage positions: one constant-velocity segment
    per pass, joined by straight moves (the printer at ``-origin_mm`` for stage 0)."""
    r = open_recording(rec)
    m = {k: v[r.order] for k, v in r.meta.items()}
    clock = FrameClock(timestamp_ns_at=int(m["timestamp_ns"][0]), print_time_s_at=t0_s,
                       how="test")
    t = t0_s + (m["timestamp_ns"] - m["timestamp_ns"][0]) * 1e-9
    xy = np.c_[m["stage_x_um"], m["stage_y_um"]] / 1000.0 + np.asarray(origin_mm)
    rows: list[list[object]] = []
    points = []
    for p in np.unique(m["pass_index"]):
        k = np.flatnonzero(m["pass_index"] == p)
        points += [(t[k[0]], xy[k[0]]), (t[k[-1]], xy[k[-1]])]
    points += [(points[-1][0] + 0.5, points[-1][1])]
    for (ta, a), (tb, b) in zip(points[:-1], points[1:], strict=True):
        dist = float(np.hypot(*(b - a)))
        d = (b - a) / dist if dist else np.zeros(2)
        rows.append([ta, tb - ta, dist / (tb - ta), 0.0, [a[0], a[1], 0.4], [d[0], d[1], 0.0]])
    return segments_from_dump(rows), clock


def test_stored_queue_places_the_frames_and_survives_a_round_trip(recorded: Path,
                                                                  tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    shutil.copytree(recorded, rec)
    before = open_recording(rec)
    seg, clock = queue_of_headers(rec, origin_mm=(50.0, 20.0))
    motion = motion_queue_for(seg, clock=clock, stage_origin_mm=(50.1, 20.0))
    add_motion_queue(rec, seg, motion)
    r = open_recording(rec)
    assert r.attrs.format_version == 5 and r.motion == motion and r.attrs.motion_queue == motion
    assert r.report.defects == 0 and r.verify() == [] and not r.report.notes
    got = [f.header for f in r.frames()]
    want = [f.header for f in before.frames()]
    # the queue wins: every frame 100 µm to -x of its header's position (origin 0.1 mm on);
    # within 0.01 µm: the simulator's time stamps are whole ns (0.5 ns at 15 mm/s: 0.0075 µm)
    for g, w in zip(got, want, strict=True):
        assert (g.frame_id, g.timestamp_ns, g.focus_index) == (w.frame_id, w.timestamp_ns,
                                                                w.focus_index)
        assert w.stage_x_um is not None
        assert g.stage_x_um == pytest.approx(w.stage_x_um - 100.0, abs=0.01)
        assert g.stage_y_um == pytest.approx(w.stage_y_um, abs=0.01)
    # the headers as recorded stay readable, and motion=False ignores the queue, saying so
    r2 = open_recording(rec, motion=False)
    assert [f.header for f in r2.frames()] == want
    assert any("motion queue is ignored" in n for n in r2.report.notes)
    assert r.header(int(r.order[0]), recorded=True) == want[0]
    with pytest.raises(MotionQueueError, match="version-4 recording only .*has one already"):
        add_motion_queue(rec, seg, motion)


def test_a_queue_that_does_not_cover_the_frames_is_refused(recorded: Path,
                                                           tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    shutil.copytree(recorded, rec)
    seg, clock = queue_of_headers(rec)
    early = clock.model_copy(update={"print_time_s_at": clock.print_time_s_at - 0.02})
    motion = motion_queue_for(seg, clock=early, stage_origin_mm=(0.0, 0.0))
    last = open_recording(rec).report.last_id
    with pytest.raises(MotionQueueError, match=r"frame_id \d+ .* not covered by the printer"):
        add_motion_queue(rec, seg, motion)
    assert open_recording(rec).attrs.format_version == 4  # nothing written
    assert not (rec / "trapq").exists()
    # a stored queue whose clock was changed after: the reader refuses, naming the frame
    add_motion_queue(rec, seg, motion_queue_for(seg, clock=clock, stage_origin_mm=(0, 0)))
    g = zarr.open_group(str(rec), mode="r+")
    attrs: dict[str, Any] = dict(g.attrs.asdict())
    attrs["motion_queue"]["clock"]["print_time_s_at"] -= 0.02
    g.update_attributes(attrs)
    with pytest.raises(RecordingError, match=r"frame_id 0 .*not covered"):
        open_recording(rec)
    assert open_recording(rec, motion=False).report.last_id == last


def test_a_version_5_recording_without_its_queue_is_refused(recorded: Path,
                                                            tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    shutil.copytree(recorded, rec)
    seg, clock = queue_of_headers(rec)
    add_motion_queue(rec, seg, motion_queue_for(seg, clock=clock, stage_origin_mm=(0, 0)))
    g = zarr.open_group(str(rec), mode="r+")
    attrs: dict[str, Any] = dict(g.attrs.asdict())
    g.update_attributes({**attrs, "motion_queue": {**attrs["motion_queue"],
                                                   "columns": ["t", "x"]}})
    with pytest.raises(MotionQueueError, match=r"motion_queue.columns is \['t', 'x'\]"):
        open_recording(rec)
    g.update_attributes({**attrs, "motion_queue": {**attrs["motion_queue"], "segments": 99}})
    with pytest.raises(MotionQueueError, match="99"):
        open_recording(rec)
    g.update_attributes(attrs)
    assert open_recording(rec).motion is not None
    shutil.rmtree(rec / "trapq")
    with pytest.raises(MotionQueueError, match="without the array 'trapq'"):
        open_recording(rec)
