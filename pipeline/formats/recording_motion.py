"""The printer's motion queue stored with a recording (format version 5), and the frames'
stage positions computed from it.

Klipper's API server streams its trapezoidal motion queue (``motion_report/dump_trapq``,
see Klipper's ``docs/API_Server.md``): each row is one segment of constant acceleration,
``[time, duration, start_velocity, acceleration, [x, y, z], [dx, dy, dz]]`` (print time s,
s, mm/s, mm/s², the start position mm, the unit direction). Gaps between moves are filled
by Klipper with null segments (no velocity), so a printing machine's queue covers every
instant. The position at print time ``t`` in a segment starting at ``t0`` is, exactly,
``start + direction * (v0 * dt + a * dt**2 / 2)`` with ``dt = t - t0`` (clamped to the
segment, as Klipper's own ``get_trapq_position``).

A recording holds the rows as the float64 array ``trapq`` (columns
:data:`~sffscan.pipeline.formats.recording.TRAPQ_COLUMNS`, CRC-32C like every array) and
the attribute ``motion_queue`` (:class:`~sffscan.pipeline.formats.recording.MotionQueue`):
the clock anchor that maps the frames' time stamps to print time and the printer position
of the stage origin. When a recording has one, the reader places every frame by it
(it wins over the stage position recorded in the frame's header: the queue is what the
printer executed, the header what the scanner was told) and refuses a recording whose
queue does not cover a usable frame's time.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from numpy.typing import ArrayLike
from sffscan.pipeline.formats.recording import (
    TRAPQ_COLUMNS,
    FrameClock,
    MotionQueue,
    RecordingAttrs,
    RecordingError,
)

__all__ = ["MotionQueueError", "segments_from_dump", "trapq_positions", "frame_print_times",
           "stage_positions_um", "trigger_print_time", "motion_queue_for", "add_motion_queue",
           "read_motion_queue", "COVER_TOL_S"]

#: segments closer than this in time abut (Klipper writes print times in full double
#: precision; 1 µs is 15 nm of travel at 15 mm/s), s
COVER_TOL_S = 1e-6
_NCOL = len(TRAPQ_COLUMNS)


class MotionQueueError(RecordingError):
    """A motion queue that is malformed, or that does not cover a frame's time (``entry``:
    the first time not covered, its position in the times asked)."""

    entry: int | None = None


def segments_from_dump(rows: Sequence[Any], *, where: str = "trapq") -> np.ndarray:
    """Klipper's ``motion_report/dump_trapq`` rows -> segments.

    Parameters
    ----------
    rows : sequence
        ``[time, duration, start_velocity, acceleration, [x, y, z], [dx, dy, dz]]`` each
        (the ``data`` of the API server's batches, any order, repeated rows allowed).
    where : str, keyword-only
        Named in the error messages.

    Returns
    -------
    segments : ndarray of float64, shape (m, 10)
        Columns :data:`TRAPQ_COLUMNS`, sorted by print time, repeated rows dropped.

    Raises
    ------
    MotionQueueError
        A row that is not of that shape, not finite, or segments that overlap.
    """
    out = np.empty((len(rows), _NCOL))
    for i, row in enumerate(rows):
        try:
            t, d, v, a, p, r = row
            out[i] = [t, d, v, a, *p, *r]
        except (TypeError, ValueError):
            raise MotionQueueError(f"{where}: row {i} is {row!r}, expected [time, duration, "
                                   "start_velocity, acceleration, [x, y, z], [dx, dy, dz]]"
                                   ) from None
    if out.size == 0:
        raise MotionQueueError(f"{where}: no segment")
    out = np.unique(out, axis=0)  # sorted by print time (then the rest), repeats dropped
    check_segments(out, where=where)
    return out


def check_segments(seg: np.ndarray, *, where: str = "trapq") -> None:
    """Raise :class:`MotionQueueError` naming the first bad row of ``seg`` (m, 10):
    not finite, a negative duration, a direction longer than 1, out of order or
    overlapping (by more than :data:`COVER_TOL_S`)."""
    if seg.ndim != 2 or seg.shape[1] != _NCOL or seg.shape[0] == 0:
        raise MotionQueueError(f"{where}: shape {list(seg.shape)}, expected [m >= 1, {_NCOL}]")
    bad = np.flatnonzero(~np.isfinite(seg).all(axis=1))
    if bad.size:
        raise MotionQueueError(f"{where}: row {bad[0]} is not finite: {seg[bad[0]].tolist()}")
    bad = np.flatnonzero(seg[:, 1] < 0)
    if bad.size:
        raise MotionQueueError(f"{where}: row {bad[0]} has a negative duration {seg[bad[0], 1]}")
    bad = np.flatnonzero(np.linalg.norm(seg[:, 7:10], axis=1) > 1 + 1e-6)
    if bad.size:
        raise MotionQueueError(f"{where}: row {bad[0]}: direction {seg[bad[0], 7:10].tolist()} "
                               "is longer than 1")
    ends = seg[:-1, 0] + seg[:-1, 1]
    bad = np.flatnonzero(seg[1:, 0] < ends - COVER_TOL_S)
    if bad.size:
        i = int(bad[0])
        raise MotionQueueError(f"{where}: rows {i} and {i + 1} overlap or are out of order "
                               f"(row {i} ends at {ends[i]:.6f} s, row {i + 1} starts at "
                               f"{seg[i + 1, 0]:.6f} s)")


def trapq_positions(segments: np.ndarray, print_time_s: ArrayLike, *,
                    where: str = "trapq") -> np.ndarray:
    """Toolhead position at print times, exactly (constant acceleration per segment).

    Parameters
    ----------
    segments : ndarray of float64, shape (m, 10)
        Sorted by print time (:func:`segments_from_dump`).
    print_time_s : array_like of float, shape (n,)
        Print times, s.

    Returns
    -------
    ndarray of float64, shape (n, 3)
        x, y, z, mm.

    Raises
    ------
    MotionQueueError
        A time outside the segments or in a gap between two of them: the message names its
        position in ``print_time_s``, the time and the span covered.
    """
    t = np.asarray(print_time_s, dtype=np.float64).reshape(-1)
    if t.size == 0:
        return np.empty((0, 3))
    i = np.searchsorted(segments[:, 0], t + COVER_TOL_S, side="right") - 1
    row = segments[np.clip(i, 0, None)]
    outside = (i < 0) | (t > row[:, 0] + row[:, 1] + COVER_TOL_S) | ~np.isfinite(t)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        err = MotionQueueError(
            f"{where}: time {t[k]:.6f} s (entry {k}, {int(outside.sum())} of {t.size} in all) "
            f"is not covered by the motion queue ({segments[0, 0]:.6f} to "
            f"{segments[-1, 0] + segments[-1, 1]:.6f} s"
            + (", in a gap between segments)" if 0 <= i[k] < len(segments) - 1 else ")"))
        err.entry = k
        raise err
    dt = np.clip(t - row[:, 0], 0.0, row[:, 1])
    dist = (row[:, 2] + 0.5 * row[:, 3] * dt) * dt
    return row[:, 4:7] + row[:, 7:10] * dist[:, None]


def frame_print_times(timestamp_ns: np.ndarray, clock: FrameClock) -> np.ndarray:
    """Print time of each frame time stamp, s (``clock``'s anchor and rate)."""
    dt = (np.asarray(timestamp_ns, dtype=np.int64) - np.int64(clock.timestamp_ns_at)) * 1e-9
    return clock.print_time_s_at + clock.rate * dt


def stage_positions_um(segments: np.ndarray, motion: MotionQueue, timestamp_ns: np.ndarray,
                       *, frame_ids: np.ndarray | None = None,
                       where: str = "trapq") -> np.ndarray:
    """Stage (x, y) of each frame time stamp from the motion queue, µm; shape (n, 2).

    Raises
    ------
    MotionQueueError
        A frame time not covered: the message names the frame (its ``frame_ids`` entry,
        when given), its time stamp and print time.
    """
    times = frame_print_times(timestamp_ns, motion.clock)
    try:
        pos = trapq_positions(segments, times, where=where)
    except MotionQueueError as err:
        t = np.asarray(times)
        k = err.entry or 0
        fid = k if frame_ids is None else int(frame_ids[k])
        raise MotionQueueError(
            f"{where}: frame_id {fid} (time stamp {int(np.asarray(timestamp_ns)[k])} ns, print "
            f"time {t[k]:.6f} s) is not covered by the printer's motion queue: its position "
            f"is unknown, the recording cannot be replayed by it ({err})") from None
    sign = np.asarray(motion.axis_sign, dtype=np.float64)
    return sign * (pos[:, :2] - np.asarray(motion.stage_origin_mm)) * 1000.0


def trigger_print_time(segments: np.ndarray, start_xy_mm: tuple[float, float], *,
                       after_s: float = -np.inf, tol_mm: float = 0.01) -> float:
    """Print time of the raster's start: the first moving segment at or after ``after_s``
    that starts at ``start_xy_mm`` after a standstill there (the macro's ``M400`` then
    ``SET_PIN``: Klipper sets the trigger pin at that instant).

    Raises
    ------
    MotionQueueError
        No such segment.
    """
    moving = (np.abs(segments[:, 2]) + np.abs(segments[:, 3])) > 0
    moving &= np.linalg.norm(segments[:, 7:9], axis=1) > 0
    at = np.hypot(segments[:, 4] - start_xy_mm[0], segments[:, 5] - start_xy_mm[1]) <= tol_mm
    still = np.r_[True, ~moving[:-1]]  # the segment before stands still
    hits = np.flatnonzero(moving & at & still & (segments[:, 0] >= after_s))
    if hits.size == 0:
        raise MotionQueueError(f"trapq: no move starts at ({start_xy_mm[0]:g}, "
                               f"{start_xy_mm[1]:g}) mm after a standstill (from "
                               f"{after_s:.3f} s): the raster's start is not in the queue")
    return float(segments[hits[0], 0])


def motion_queue_for(segments: np.ndarray, *, clock: FrameClock,
                     stage_origin_mm: tuple[float, float],
                     axis_sign: tuple[int, int] = (1, 1), name: str = "toolhead",
                     source: str = "klipper motion_report/dump_trapq") -> MotionQueue:
    """The ``motion_queue`` attribute describing ``segments``."""
    return MotionQueue.model_validate({
        "source": source, "name": name, "segments": int(segments.shape[0]),
        "start_s": float(segments[0, 0]), "end_s": float(segments[-1, 0] + segments[-1, 1]),
        "clock": clock, "stage_origin_mm": stage_origin_mm, "axis_sign": axis_sign})


def add_motion_queue(path: str | Path, segments: np.ndarray, motion: MotionQueue) -> None:
    """Store the motion queue in a closed version-4 recording (which becomes version 5).

    Every usable frame's time must be covered (checked before anything is written).

    Raises
    ------
    MotionQueueError
        The recording is still being written, is of version < 4, has a motion queue
        already (never overwritten), or the queue does not cover its frames.
    """
    from sffscan.pipeline.formats.recording_reader import open_recording

    where = str(path)
    check_segments(segments, where=f"{where}/trapq")
    rec = open_recording(path, motion=False)
    if rec.attrs.status == "recording":
        raise MotionQueueError(f"{where}: still being written (status 'recording')")
    if rec.attrs.format_version != 4:
        raise MotionQueueError(f"{where}: format version {rec.attrs.format_version}; a motion "
                               "queue goes into a version-4 recording only"
                               + (" (it has one already)" if rec.attrs.motion_queue else ""))
    stage_positions_um(segments, motion, rec.meta["timestamp_ns"][rec.order],
                       where=f"{where}/trapq")
    group = zarr.open_group(where, mode="r+")
    from zarr.codecs import Crc32cCodec

    arr = group.create_array(name="trapq", shape=segments.shape, chunks=segments.shape,
                             dtype="float64", compressors=[Crc32cCodec()],
                             dimension_names=("segment", "field"),
                             attributes={"columns": list(TRAPQ_COLUMNS)})
    arr[...] = segments
    attrs = RecordingAttrs.model_validate({**group.attrs.asdict(), "format_version": 5,
                                           "motion_queue": motion.model_dump(mode="json")})
    group.update_attributes(attrs.model_dump(mode="json", exclude_none=True))


def read_motion_queue(group: zarr.Group, attrs: RecordingAttrs,
                      where: str) -> tuple[np.ndarray, MotionQueue] | None:
    """The segments and their description of a version-5 recording (None before)."""
    if attrs.format_version < 5:
        return None
    if attrs.motion_queue is None:
        raise MotionQueueError(f"{where}: format version 5 without the attribute "
                               "'motion_queue'")
    try:
        node = group.get("trapq")
        seg = None if not isinstance(node, zarr.Array) else np.asarray(node[...], np.float64)
    except Exception as exc:  # noqa: BLE001 - a corrupt chunk (CRC) or metadata
        raise MotionQueueError(f"{where}/trapq: unreadable ({type(exc).__name__}: {exc})"
                               ) from None
    if seg is None:
        raise MotionQueueError(f"{where}: format version 5 without the array 'trapq'")
    check_segments(seg, where=f"{where}/trapq")
    if tuple(attrs.motion_queue.columns) != TRAPQ_COLUMNS:
        raise MotionQueueError(f"{where}: attribute motion_queue.columns is "
                               f"{list(attrs.motion_queue.columns)}, this reader knows "
                               f"{list(TRAPQ_COLUMNS)}")
    if seg.shape[0] != attrs.motion_queue.segments:
        raise MotionQueueError(f"{where}/trapq: {seg.shape[0]} rows, the attribute "
                               f"motion_queue.segments says {attrs.motion_queue.segments}")
    return seg, attrs.motion_queue

