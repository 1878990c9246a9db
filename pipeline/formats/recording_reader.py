"""Reading a recording (:mod:`sffscan.pipeline.formats.recording`): :func:`open_recording`
validates it and reports every defect (see that module's notes); :class:`Recording` gives
its usable frames in frame_id order, checks that each frame is where it belongs (version 4)
and paces a replay by the time stamps. The per-frame metadata is read, and what is damaged
rebuilt, by :mod:`~sffscan.pipeline.formats.recording_repair`."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zarr
from pydantic import ValidationError
from sffscan.pipeline.config import ConfigError, ScanConfig, config_from_dict
from sffscan.pipeline.formats.recording import (
    BASE_COLUMNS,
    FORMAT,
    GROW,
    HEADER_COLUMNS,
    PER_FRAME,
    MotionQueue,
    RecordingAttrs,
    RecordingError,
    RecordingReport,
    _array,
    _chunk_keys,
    _ids,
    _stored,
    header_row,
)
from sffscan.pipeline.formats.recording_checks import (
    Pacer,
    frame_digest,
    timestamp_defects,
)
from sffscan.pipeline.formats.recording_motion import read_motion_queue, stage_positions_um
from sffscan.pipeline.formats.recording_repair import read_frame_metadata
from sffscan.pipeline.formats.zarr_chunks import Plans, read_into, read_many
from sffscan.stages.frame_source import FrameBuffers, SourceFrames
from sffscan.stages.messages import Frame, FrameHeader

if TYPE_CHECKING:
    from sffscan.pipeline.completeness import FrameAccount

log = logging.getLogger(__name__)


@dataclass
class Recording:
    """An opened, validated recording: attributes, configuration, usable frames in order."""

    path: Path
    attrs: RecordingAttrs
    config: ScanConfig
    report: RecordingReport
    group: zarr.Group
    #: array indexes of the usable frames, in replay (frame_id) order
    order: np.ndarray
    meta: dict[str, np.ndarray]
    #: the printer's motion queue (version 5, unless opened with ``motion=False``) and the
    #: stage (x, y) µm it gives each entry (NaN: not a usable frame); it wins over the
    #: positions in the headers
    motion: MotionQueue | None = None
    motion_xy_um: np.ndarray | None = None

    @property
    def recording_id(self) -> str | None:
        """The recording's unique id (None for a recording made before version 4)."""
        return self.attrs.recording_id

    def _headers(self) -> zarr.Array | None:
        """The ``headers`` array when its copies hold the index and digest (version 4)."""
        if self.attrs.format_version < 4:
            return None
        arr = _array(self.group, "headers", str(self.path))
        if arr is None or arr.ndim != 2 or arr.shape[1] != len(HEADER_COLUMNS):
            return None
        return arr

    def _check_place(self, headers: zarr.Array, index: int, image: np.ndarray,
                     fid: int, *, plans: Plans | None = None) -> str | None:
        """Why the frame at ``index`` is not where it belongs (None if it is, or if its
        header copy is unreadable: a lost copy loses no frame, the CRC still holds)."""
        try:
            row = read_many([(headers, index)], plans=plans)[0]
        except Exception:  # noqa: BLE001 - an unreadable copy: reported by verify()
            return None
        if int(row[0]) < 0:  # no copy (lost): nothing to check against
            return None
        enc = headers.metadata.encode_chunk_key  # type: ignore[union-attr]
        if int(row[BASE_COLUMNS]) != index or int(row[0]) != fid:
            return (f"frame index {index} (frame_id {fid}): its header copy "
                    f"{self.path}/headers/{enc((index, 0))} holds index "
                    f"{int(row[BASE_COLUMNS])}, frame_id {int(row[0])} (a header chunk "
                    "swapped or copied)")
        want = frame_digest(image, index=index, recording_id=self.recording_id)
        if int(row[BASE_COLUMNS + 1]) != want:
            # the frames array opened only to name the chunk (opening it for every frame
            # took half of the frame reader's CPU in a profile of the test suite)
            frames = self.group["frames"]
            key = frames.metadata.encode_chunk_key((index, 0, 0))  # type: ignore[union-attr]
            return (f"frame index {index} (frame_id {fid}): {self.path}/frames/{key} holds "
                    "pixels that are not this frame's (digest mismatch: a frame chunk "
                    "swapped with or copied over another)")
        return None

    def header(self, index: int, *, recorded: bool = False) -> FrameHeader:
        """The header of the frame at array ``index``: its stage position from the motion
        queue when there is one, unless ``recorded`` (the header as recorded)."""
        m = self.meta
        sx, sy = float(m["stage_x_um"][index]), float(m["stage_y_um"][index])
        if self.motion_xy_um is not None and not recorded:
            sx, sy = (float(v) for v in self.motion_xy_um[index])
        return FrameHeader(frame_id=int(m["frame_id"][index]),
                           timestamp_ns=int(m["timestamp_ns"][index]),
                           focus_index=int(m["focus_index"][index]),
                           stage_x_um=None if np.isnan(sx) else sx,
                           stage_y_um=None if np.isnan(sy) else sy,
                           pass_index=int(m["pass_index"][index]))

    def frames(self, *, realtime: bool = False, start: int = 0,
               clock: Callable[[], float] = time.monotonic,
               sleep: Callable[[float], None] = time.sleep) -> SourceFrames:
        """The usable frames in frame_id order, from the ``start``-th; each decoded
        straight into an array of the iterator's ``buffers``
        (:class:`~sffscan.stages.frame_source.FrameBuffers`: new arrays, or the process
        placement's frame ring, which then takes no copy).

        A frame whose chunk cannot be decoded is left out (a lost frame for the pipeline)
        and its frame_id added to ``report.corrupt``; so is a frame whose pixels are not the
        ones its header copy's digest names (version 4: ``report.misplaced``, a warning names
        the frame index and file). ``realtime`` paces the frames by their time stamps, each
        step bounded (:class:`~sffscan.pipeline.formats.recording_checks.Pacer`; ``clock``
        and ``sleep`` are replaceable for tests)."""
        buffers = FrameBuffers()
        return SourceFrames(self._frames(buffers, realtime=realtime, start=start,
                                         clock=clock, sleep=sleep), buffers)

    def _frames(self, buffers: FrameBuffers, *, realtime: bool, start: int,
                clock: Callable[[], float], sleep: Callable[[float], None]
                ) -> Iterator[Frame]:
        arr = _array(self.group, "frames", str(self.path))
        assert arr is not None
        shape = self.attrs.frame_shape
        headers = self._headers()
        pacer = Pacer(self.config.optics.fps, clock=clock, sleep=sleep) if realtime else None
        plans = Plans()  # the two arrays' chunk plans, worked out once for the stream
        for index in self.order[start:]:
            header = self.header(int(index))
            # the array first, outside the try: a runtime that cannot give one (stopped,
            # its ring starved) stops the replay; it is not a corrupt frame
            out = buffers.empty(tuple(shape), arr.dtype)
            try:
                # chunk by chunk without zarr's event loop (zarr_chunks: the same values)
                if tuple(arr.shape[1:]) != tuple(shape):
                    raise ValueError(f"shape {tuple(arr.shape[1:])}")
                image = read_into(arr, int(index), out, plans=plans)
            except Exception:  # noqa: BLE001 - undecodable or truncated chunk
                if header.frame_id not in self.report.corrupt:
                    self.report.corrupt.append(header.frame_id)
                    self.report.frames -= 1  # not usable after all
                continue
            if headers is not None:
                why = self._check_place(headers, int(index), image, header.frame_id,
                                        plans=plans)
                if why is not None:
                    if header.frame_id not in self.report.misplaced:
                        self.report.misplaced.append(header.frame_id)
                        self.report.frames -= 1
                        self.report.notes.append(why)
                        log.warning("%s; the frame is left out (lost)", why)
                    continue
            if pacer is not None:
                pacer.wait(header.frame_id, header.timestamp_ns)
            yield Frame(header, image)

    def account(self) -> FrameAccount:
        """Frames a replay should have: what the live scan expected (``frames_planned``),
        else the recorded configuration's plan."""
        from sffscan.pipeline.completeness import FrameAccount, planned_frames

        planned = self.attrs.frames_planned
        return FrameAccount(planned=planned if planned is not None
                            else planned_frames(self.config))

    def verify(self) -> list[int]:
        """Decode every usable frame; frame ids of the corrupt ones (also in the report).

        Version 2: every header copy is decoded and compared with the frame's metadata too;
        a corrupt or disagreeing copy is a note (the frame itself is still usable). Version
        4: a frame whose pixels are not its header copy's digest's is in ``report.misplaced``
        (and the returned list)."""
        before = len(self.report.corrupt)
        before_misplaced = len(self.report.misplaced)
        for _ in self.frames():
            pass
        headers = _array(self.group, "headers", str(self.path)) \
            if self.attrs.format_version >= 2 else None
        if headers is not None and headers.ndim == 2:
            bad: list[int] = []
            for index in self.order:
                want = header_row(self.header(int(index), recorded=True))
                try:
                    got = np.asarray(headers[int(index)], dtype=np.int64)
                except Exception:  # noqa: BLE001 - undecodable or truncated chunk
                    got = None
                if got is not None and got.size > BASE_COLUMNS \
                        and got[BASE_COLUMNS] != int(index):
                    got = None  # a copy that belongs to another index
                if got is None or not np.array_equal(got[:BASE_COLUMNS], want):
                    bad.append(int(want[0]))
            if bad:
                self.report.notes.append(f"header copies: {len(bad)} corrupt, lost or not "
                                         "matching the metadata (the frames are usable): "
                                         "frame_id " + _ids([str(i) for i in bad]))
        return self.report.corrupt[before:] + self.report.misplaced[before_misplaced:]


def open_recording(path: str | Path, *, motion: bool = True) -> Recording:
    """Open and validate a recording.

    ``motion``: place the frames by the printer's motion queue when the recording has one
    (version 5, :mod:`~sffscan.pipeline.formats.recording_motion`); False ignores it (the
    headers' stage positions, a note says so).

    Raises
    ------
    RecordingError
        The path is not a recording, an attribute is invalid, the ``frames`` array or a
        required per-frame array is missing, the frames' shape or dtype disagrees with the
        attributes or the configuration, or no frame is usable; the motion queue is
        malformed or does not cover a usable frame's time (``MotionQueueError``, naming the
        frame).
    """
    p = Path(path)
    where = str(p)
    if not p.exists():
        raise RecordingError(f"{where}: no such recording")
    try:
        group = zarr.open_group(where, mode="r")
        raw = group.attrs.asdict()
    except Exception as exc:  # noqa: BLE001 - anything that is not a readable group
        name = f"{where}/zarr.json" if (p / "zarr.json").exists() else where
        raise RecordingError(f"{name}: not a readable Zarr v3 group "
                             f"({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise RecordingError(f"{where}/zarr.json: the attributes are not a JSON object")
    if raw.get("format") != FORMAT:
        raise RecordingError(f"{where}: attribute 'format' is {raw.get('format')!r}, "
                             f"expected {FORMAT!r} (not an sffscan recording)")
    try:
        attrs = RecordingAttrs.model_validate(raw)
    except ValidationError as err:
        e = err.errors()[0]
        loc = ".".join(str(x) for x in e["loc"])
        raise RecordingError(f"{where}: attribute '{loc}': {e['msg']}") from err
    try:
        cfg = config_from_dict(dict(attrs.scan_config), origin=f"{where} attribute scan_config")
    except ConfigError as err:
        raise RecordingError(str(err)) from err
    o = cfg.optics
    if tuple(attrs.frame_shape) != (o.height_px, o.width_px):
        raise RecordingError(f"{where}: attribute frame_shape {list(attrs.frame_shape)} "
                             f"disagrees with scan_config optics (height_px, width_px) = "
                             f"[{o.height_px}, {o.width_px}]")
    if attrs.dtype != o.dtype:
        raise RecordingError(f"{where}: attribute dtype {attrs.dtype} disagrees with "
                             f"scan_config optics.bit_depth {o.bit_depth} ({o.dtype})")
    frames = _array(group, "frames", where)
    if frames is None:
        raise RecordingError(f"{where}: array 'frames' is missing")
    if frames.ndim != 3 or tuple(frames.shape[1:]) != tuple(attrs.frame_shape):
        raise RecordingError(f"{where}: array 'frames' has shape {list(frames.shape)}, expected "
                             f"[n, {attrs.frame_shape[0]}, {attrs.frame_shape[1]}] "
                             "(attribute frame_shape)")
    if frames.dtype != np.dtype(attrs.dtype):
        raise RecordingError(f"{where}: array 'frames' has dtype {frames.dtype}, the attribute "
                             f"dtype says {attrs.dtype}")
    report = RecordingReport(where, attrs.status)
    if attrs.status == "recording":
        report.notes.append("status 'recording': the recorder did not close it (killed or "
                            "crashed?); replaying up to its last complete frame")
    elif attrs.status == "failed":
        report.notes.append(f"status 'failed': {attrs.error or 'the scan stopped on an error'}")
    arrays: dict[str, zarr.Array] = {}
    for name, (_, _, required) in PER_FRAME.items():
        arr = _array(group, name, where)
        if arr is None:
            if required or (name == "pass_index" and cfg.motion.passes > 1):
                raise RecordingError(f"{where}: per-frame array '{name}' is missing")
            continue
        if arr.ndim != 1:
            raise RecordingError(f"{where}: per-frame array '{name}' has shape "
                                 f"{list(arr.shape)}, expected one dimension")
        kind = np.dtype(PER_FRAME[name][0]).kind
        if arr.dtype.kind not in (("i", "u") if kind == "i" else ("f",)):
            raise RecordingError(f"{where}: per-frame array '{name}' has dtype {arr.dtype}, "
                                 f"expected {PER_FRAME[name][0]}")
        arrays[name] = arr
    for name in ("stage_x_um", "stage_y_um"):
        if name not in arrays:
            report.notes.append(f"no '{name}' array: frames are placed by the speed model")
    n = min([int(frames.shape[0])] + [int(a.shape[0]) for a in arrays.values()])
    longer = [f"{k} ({a.shape[0]})" for k, a in {"frames": frames, **arrays}.items()
              if a.shape[0] > n]
    frame_keys = _chunk_keys(frames)
    n, meta, bad = read_frame_metadata(group, frames, arrays, frame_keys, n, attrs=attrs,
                                       where=where, report=report)
    fid = meta["frame_id"]
    written = (fid >= 0) & (meta["timestamp_ns"] >= 0) & (meta["focus_index"] >= 0)
    written &= meta["pass_index"] >= 0
    written[list(bad)] = False
    idx = np.flatnonzero(written)
    # entries up to the last written one, an unreadable one or the count the writer stated
    # when it closed are expected: those without metadata are defects, not an unwritten tail
    claimed = attrs.frames or 0
    if claimed > n:
        report.notes.append(f"attribute frames says {claimed} but the arrays hold "
                            f"{n} entries")
        if claimed > n + GROW:  # a claim no chunk file supports: not listed entry by entry
            report.claimed_entries, claimed = claimed, n
    last_written = max(int(idx[-1]) + 1 if idx.size else 0, max(bad) + 1 if bad else 0,
                       claimed)
    report.entries = last_written
    report.unwritten = max(0, n - last_written)
    report.missing_metadata = [i for i in range(last_written) if i >= n or not written[i]]
    if longer:
        report.notes.append("arrays longer than the per-frame metadata (entries beyond "
                            f"{n} have no metadata and are not replayed): " + ", ".join(longer))
    # frames whose chunk is absent (another writer, or a lost file) are not replayed
    # (every chunk of the frame: a frame split over several chunks must be whole)
    keys = frame_keys
    enc = frames.metadata.encode_chunk_key  # type: ignore[union-attr]
    per_chunk, cy, cx = _stored(frames)
    tiles = [(y, x) for y in range(-(-attrs.frame_shape[0] // cy))
             for x in range(-(-attrs.frame_shape[1] // cx))]
    whole = np.array([all(enc((int(i) // per_chunk, y, x)) in keys for y, x in tiles)
                      for i in idx], dtype=bool)
    report.missing_chunks = [int(fid[i]) for i in idx[~whole]]
    idx = idx[whole]
    # storage order -> frame_id order; the first copy of a repeated frame_id is kept
    ids = fid[idx]
    running_max = np.maximum.accumulate(ids) if ids.size else ids
    late = np.flatnonzero(ids[1:] < running_max[:-1]) + 1 if ids.size > 1 else np.array([], int)
    _, first = np.unique(ids, return_index=True)
    dup_mask = np.ones(ids.size, bool)
    dup_mask[first] = False
    report.duplicates = [int(v) for v in ids[dup_mask]]
    report.out_of_order = sorted({int(ids[i]) for i in late if not dup_mask[i]})
    keep = np.sort(first)
    order = idx[keep][np.argsort(ids[keep], kind="stable")]
    if order.size == 0:
        raise RecordingError(f"{where}: no usable frame (entries {n}, written {last_written})")
    sorted_ids = fid[order]
    steps = np.diff(sorted_ids)
    report.gaps = [(int(sorted_ids[i]) + 1, int(steps[i]) - 1) for i in np.flatnonzero(steps > 1)]
    report.frames = int(order.size)
    report.first_id, report.last_id = int(sorted_ids[0]), int(sorted_ids[-1])
    ts = meta["timestamp_ns"][order]
    report.time_backwards, report.time_jumps = timestamp_defects(sorted_ids, ts, o.fps)
    # a frame without a stage position is placed by the speed model from its time stamp:
    # with a wrong one it would land elsewhere (or stop the scan as moving backwards)
    queue = read_motion_queue(group, attrs, where) if motion else None
    if attrs.format_version >= 5 and not motion:
        report.notes.append("the printer's motion queue is ignored (motion=False): frames "
                            "are placed by their headers")
    wrong = set(report.time_backwards) | set(report.time_jumps)
    drop = np.array([int(i) in wrong and (queue is not None or np.isnan(meta["stage_x_um"][k]))
                     for i, k in zip(sorted_ids, order, strict=True)], dtype=bool)
    if drop.any():
        report.time_left_out = [int(i) for i in sorted_ids[drop]]
        report.notes.append(f"{int(drop.sum())} frame(s) without a stage position and with a "
                            "wrong time stamp (placed by it) are left out (lost): frame_id "
                            + _ids([str(i) for i in report.time_left_out]))
        order, sorted_ids, ts = order[~drop], sorted_ids[~drop], ts[~drop]
        report.frames = int(order.size)
        if order.size == 0:
            raise RecordingError(f"{where}: no usable frame (every time stamp is wrong)")
    report.duration_s = float(ts.max() - ts.min()) * 1e-9
    xy = None
    if queue is not None:
        xy = np.full((n, 2), np.nan)
        xy[order] = stage_positions_um(queue[0], queue[1], ts, frame_ids=sorted_ids,
                                       where=f"{where}/trapq")
    return Recording(p, attrs, cfg, report, group, order, meta,
                     None if queue is None else queue[1], xy)
