"""Checks of a recording that its chunks' CRCs cannot make: identity, lengths, time stamps.

- Identity (format version 4): a recording has a ``recording_id`` (uuid4 hex) and every
  frame's header copy holds the frame's array index and a digest of its pixels bound to that
  index and to the recording id (:func:`frame_digest`). Each chunk's CRC-32C proves the chunk
  intact, not that it is where it belongs: a frame chunk swapped with another, or copied over
  another (even from another recording of the same shape), has a valid CRC but not the
  digest its header copy holds.
- Claimed lengths (:func:`stored_extent`): the entries an array's ``zarr.json`` claims are
  checked against the chunk files present, so a metadata file claiming 2**40 entries costs
  nothing (entries beyond the last stored chunk hold no data).
- Time stamps (:func:`timestamp_defects`, :class:`Pacer`): in frame_id order the time stamps
  must not go back, nor jump by more than a plausible time (:data:`JUMP_FACTOR` times the
  nominal frame interval of the frame_id step, plus :data:`JUMP_MARGIN_S`); a replay paced
  by them (``--realtime``) never waits longer than the plausible time of a step.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import google_crc32c
import numpy as np

log = logging.getLogger(__name__)

#: a time stamp step is implausible beyond this many nominal frame intervals ...
JUMP_FACTOR = 100.0
#: ... plus this margin, s (a stop-and-go scan pauses between stacks)
JUMP_MARGIN_S = 10.0


def frame_digest(image: np.ndarray, *, index: int, recording_id: str | None) -> int:
    """CRC-32C of the frame's array index (int64, little endian), the recording id (ASCII)
    and the pixels (C order, native byte order): binds a frame's content to its place.

    Parameters
    ----------
    image : ndarray, (H, W), uint8 or uint16
        The frame's pixels.
    index : int
        The frame's index in the recording's arrays (not its frame_id).
    recording_id : str or None
        The recording's id.

    Returns
    -------
    int
        The digest, 0 <= value < 2**32.
    """
    crc = google_crc32c.value(np.int64(index).astype("<i8").tobytes()
                              + (recording_id or "").encode("ascii"))
    view = np.ascontiguousarray(image).view()
    view.flags.writeable = False  # google_crc32c reads read-only buffers without a copy
    return int(google_crc32c.extend(crc, view))


def stored_extent(first_indexes: set[int], chunk_len: int) -> int:
    """Entries covered by the stored chunks of an array along its first axis: one past the
    last entry of the last chunk present (0 when none is)."""
    return (max(first_indexes) + 1) * chunk_len if first_indexes else 0


def plausible_step_s(id_step: int, fps: float) -> float:
    """Longest plausible time between two frames ``id_step`` frame_ids apart, s."""
    return JUMP_FACTOR * max(id_step, 1) / fps + JUMP_MARGIN_S


def timestamp_defects(ids: np.ndarray, ts_ns: np.ndarray,
                      fps: float) -> tuple[list[int], list[int]]:
    """Frames whose time stamp goes back, and frames whose time stamp jumps forward more
    than :func:`plausible_step_s`, in frame_id order.

    Each frame is compared with the last good one before it: a frame that goes back is not
    a reference for the next, and a jump followed by a frame that goes back to the line of
    the frames before it is a single wrong time stamp (a spike), flagged alone.

    Parameters
    ----------
    ids : ndarray, (n,), int64
        frame_id of the usable frames, increasing.
    ts_ns : ndarray, (n,), int64
        Their time stamps, ns.
    fps : float
        Nominal frame rate, frames/s.

    Returns
    -------
    backwards, jumps : list of int
        frame_id of the frames concerned.
    """
    backwards: list[int] = []
    jumps: list[int] = []
    idl = [int(i) for i in ids]
    t = [int(v) for v in ts_ns]

    def fits(i: int, ref: int) -> bool:
        dt = (t[i] - t[ref]) * 1e-9
        return 0 <= dt <= plausible_step_s(idl[i] - idl[ref], fps)

    ref = 0
    for i in range(1, len(idl)):
        if t[i] < t[ref]:
            backwards.append(idl[i])
            continue
        if not fits(i, ref):
            jumps.append(idl[i])
            if i + 1 < len(idl) and t[i + 1] < t[i] and fits(i + 1, ref):
                continue  # a spike: the next frame is back on the line of the good ones
        ref = i
    return backwards, jumps


class Pacer:
    """Paces frames by their time stamps (``replay --realtime``), each step bounded.

    The wait before a frame is its time stamp's step from the previous frame; a step that
    goes back, or that is longer than :func:`plausible_step_s`, is replaced by the nominal
    frame interval of its frame_id step and logged as a warning naming the frame; and the
    time since the first frame never exceeds the plausible time of the whole frame_id span
    (:func:`plausible_step_s` of it). So a replay never waits longer than the plausible
    duration of the recorded scan plus :data:`JUMP_MARGIN_S`.
    """

    def __init__(self, fps: float, *, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.fps = fps
        self.clock = clock
        self.sleep = sleep
        self._target: float | None = None
        self._start: tuple[float, int] = (0.0, 0)  # wall time and frame_id of the first frame
        self._prev: tuple[int, int] | None = None
        self.replaced: list[int] = []  # frame_id of the steps replaced

    def wait(self, frame_id: int, timestamp_ns: int) -> None:
        """Sleep until the frame's time (relative to the first frame's)."""
        now = self.clock()
        if self._target is None or self._prev is None:
            self._target, self._prev = now, (frame_id, timestamp_ns)
            self._start = (now, frame_id)
            return
        prev_id, prev_ts = self._prev
        step = (timestamp_ns - prev_ts) * 1e-9
        nominal = max(frame_id - prev_id, 1) / self.fps
        if step < 0 or step > plausible_step_s(frame_id - prev_id, self.fps):
            self.replaced.append(frame_id)
            what = "goes back" if step < 0 else "jumps forward"
            log.warning("replay --realtime: frame_id %d: time stamp %s by %.3g s from "
                        "frame_id %d; paced at the nominal %.3g s instead", frame_id, what,
                        abs(step), prev_id, nominal)
            step = nominal
        self._prev = (frame_id, timestamp_ns)
        t0, first = self._start
        self._target = min(self._target + step,
                           t0 + plausible_step_s(frame_id - first, self.fps))
        delay = self._target - now
        if delay > 0:
            self.sleep(delay)
