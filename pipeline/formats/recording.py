"""Raw-stream recordings: the format (a Zarr v3 group) and a validating reader.

Layout (format ``sffscan-recording``, version 4, or 5 once the printer's motion queue is
added; schema ``schemas/recording_attrs.v1.json``):

- ``frames``: uint8 or uint16 (n, H, W), one frame per chunk; version 3 names the chunks of
  ``frames`` and ``headers`` with the separator ``.`` (``frames/c.i.0.0``, every chunk in the
  array's folder), versions 1 and 2 with ``/`` (``frames/c/i/0/0``, a folder per frame);
  zarr reads each array's encoding from its ``zarr.json``;
- ``headers`` (versions 2 to 4): int64 (n, 6) or (n, 8), one chunk per frame beside it: a copy
  of the frame's header (frame_id, timestamp_ns, focus_index, stage_x_um and stage_y_um as the
  bits of float64, pass_index; -1 = not written), written right after the frame's chunk;
  version 4 adds the frame's array index and the digest of its pixels bound to that index
  and to the recording id (:func:`~sffscan.pipeline.formats.recording_checks.frame_digest`):
  a frame chunk swapped with another or copied over another is detected;
- ``frame_id``: int64 (n,), the camera's frame counter; ``-1`` (the fill value) = not written;
- ``timestamp_ns``: int64 (n,), exposure time stamp, ns;
- ``focus_index``: int32 (n,), focus level of the lens staircase;
- ``stage_x_um``, ``stage_y_um``: float64 (n,), commanded stage position, µm; NaN = none
  (optional arrays: without them frames are placed by the speed model);
- ``pass_index``: int32 (n,) (optional when the configuration has one pass);
- ``trapq`` (version 5): float64 (m, 10), the printer's motion queue over the scan
  (Klipper's ``motion_report/dump_trapq``, columns :data:`TRAPQ_COLUMNS`), with the
  attribute ``motion_queue`` (:class:`MotionQueue`: the frames' clock and the stage
  origin); added to a closed version-4 recording, it places the frames in a replay
  (:mod:`~sffscan.pipeline.formats.recording_motion`);
- group attributes (:class:`RecordingAttrs`): format, version, status, frame shape and dtype,
  the whole scan configuration and (version 4) ``recording_id``, a uuid4 drawn when the
  recording is created (:func:`read_recording_id`).

Integrity (versions 2 and 3): every chunk of every array ends with a CRC-32C (zarr v3's ``crc32c``
codec): a flipped byte makes the chunk undecodable, never silently different. No single
chunk file is a single point of failure: the per-frame arrays are cut in small chunks
(:data:`META_CHUNK` frames) and every frame's header has a copy beside the frame, so a lost
or corrupt metadata chunk is rebuilt from the copies, and a lost or corrupt frame or header
chunk loses that frame only. Every chunk is written with ``write_empty_chunks``: within
the frames written, an absent chunk is a lost one. Version-1 recordings (no checksums, no
header copies) still replay.

Entry ``i`` of every per-frame array describes ``frames[i]``. Arrays may be longer than what
was written (the recorder grows them in steps): entries whose ``frame_id`` is -1 are not
frames. The reader (:func:`sffscan.pipeline.formats.recording_reader.open_recording`)
validates all of it and reports every defect with counts and frame ids: frame-id gaps,
duplicated and out-of-order frames, corrupt or
truncated chunks, missing chunks or metadata, a shape or dtype that disagrees with the
attributes, frames misplaced (version 4), time stamps that go back or jump implausibly,
array lengths the chunk files present do not support
(:mod:`~sffscan.pipeline.formats.recording_checks`). The reader lives in
:mod:`~sffscan.pipeline.formats.recording_reader` (and is imported from here). What is
recoverable is reported and left out (never filled); what is not raises
:class:`RecordingError` naming the array, attribute or frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import zarr
from pydantic import BaseModel, ConfigDict, Field
from sffscan.stages.messages import FrameHeader

if TYPE_CHECKING:
    from sffscan.pipeline.formats.recording_reader import Recording

__all__ = ["FORMAT", "FORMAT_VERSION", "TRAPQ_COLUMNS", "FrameClock", "MotionQueue",
           "PER_FRAME", "META_CHUNK", "GROW", "HEADER_COLUMNS",
           "BASE_COLUMNS", "RecordingAttrs", "RecordingError", "RecordingReport",
           "header_row", "read_recording_id", "chunk_keys_from",
           "annotate_mosaic"]

FORMAT = "sffscan-recording"
FORMAT_VERSION = 4
#: per-frame arrays: name -> (dtype, fill value, required)
PER_FRAME: dict[str, tuple[str, Any, bool]] = {
    "frame_id": ("int64", -1, True),
    "timestamp_ns": ("int64", -1, True),
    "focus_index": ("int32", -1, True),
    "stage_x_um": ("float64", float("nan"), False),
    "stage_y_um": ("float64", float("nan"), False),
    "pass_index": ("int32", -1, False),
}
#: chunk length of the per-frame arrays written by the recorder, frames (uncompressed)
META_CHUNK = 256
#: the recorder grows its arrays this many frames at a time: a recording cut short may
#: claim up to this many entries past its last chunk file
GROW = 1024
#: columns of the ``headers`` array (versions 2 and 3: the first 6; version 4: all), in order
HEADER_COLUMNS = ("frame_id", "timestamp_ns", "focus_index", "stage_x_um", "stage_y_um",
                  "pass_index", "index", "digest")
#: the header's own columns (the copy of the :class:`FrameHeader`)
BASE_COLUMNS = 6
#: pattern of a recording id (uuid4, hex)
RECORDING_ID_PATTERN = r"^[0-9a-f]{32}$"


#: columns of the ``trapq`` array (version 5): one row per segment of Klipper's
#: trapezoidal motion queue (``motion_report/dump_trapq``: time, duration, start_velocity,
#: acceleration, start_position (x, y, z), direction (x, y, z))
TRAPQ_COLUMNS = ("print_time_s", "duration_s", "start_v_mm_s", "accel_mm_s2", "start_x_mm",
                 "start_y_mm", "start_z_mm", "dir_x", "dir_y", "dir_z")


class FrameClock(BaseModel):
    """How a frame's time stamp maps to the printer's print time:
    ``print_time_s = print_time_s_at + rate * (timestamp_ns - timestamp_ns_at) * 1e-9``."""

    model_config = ConfigDict(extra="forbid")

    timestamp_ns_at: int = Field(description="A frame time stamp of the anchor, ns")
    print_time_s_at: float = Field(description="The printer's print time at that instant, s")
    rate: float = Field(1.0, gt=0.5, lt=2.0, description="Print-time seconds per time-stamp "
                        "second (clock rate ratio; 1 unless measured)")
    how: str = Field("", description="Where the anchor comes from, e.g. 'trigger': the first "
                     "frame exposed at the trigger pin's edge, the start of the raster's "
                     "first move")


class MotionQueue(BaseModel):
    """The printer's motion queue stored with a recording (array ``trapq``, version 5)."""

    model_config = ConfigDict(extra="forbid")

    source: str = Field("klipper motion_report/dump_trapq", description="Where the rows "
                        "come from")
    name: str = Field("toolhead", description="The motion queue's name (Klipper's trapq)")
    columns: tuple[str, ...] = Field(TRAPQ_COLUMNS, description="Columns of 'trapq'")
    segments: int = Field(ge=1, description="Rows of the array 'trapq'")
    start_s: float = Field(description="Print time the rows cover from, s")
    end_s: float = Field(description="Print time the rows cover up to, s")
    clock: FrameClock
    stage_origin_mm: tuple[float, float] = Field(
        description="Printer (x, y) at which the stage position is (0, 0), mm: "
        "stage_x_um = axis_sign[0] * (x_mm - stage_origin_mm[0]) * 1000, likewise y")
    axis_sign: tuple[Literal[-1, 1], Literal[-1, 1]] = Field(
        (1, 1), description="Sign of the stage axes against the printer's x and y")


class RecordingAttrs(BaseModel):
    """Attributes of a raw-stream recording Zarr group (format ``sffscan-recording``)."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["sffscan-recording"] = "sffscan-recording"
    format_version: Literal[1, 2, 3, 4, 5] = Field(
        4, description="5: as 4, with the printer's motion queue over the scan (array "
        "'trapq' and attribute 'motion_queue'; added after the scan, a replay places the "
        "frames by it); 4: as 3, with a recording_id and each frame's header copy holding "
        "its array index and a digest of its pixels bound to the index and the id; "
        "3: as 2, with the chunks of 'frames' and 'headers' named 'c.i.0.0' "
        "(zarr's default chunk key encoding with the separator '.', every chunk in the "
        "array's folder); 2: CRC-32C on every chunk and a copy of each frame's header beside "
        "it (array 'headers'), chunk keys 'c/i/0/0'; 1: neither (still replayed)")
    status: Literal["recording", "complete", "failed"] = Field(
        "complete", description="'recording' while being written (still so after a crash: "
        "the frames up to the last complete one are readable); 'complete' after a clean end; "
        "'failed' if the scan or the recorder stopped on an error")
    frame_shape: tuple[int, int] = Field(description="Frame (height, width), px")
    dtype: Literal["uint8", "uint16"] = Field(description="Frame pixel type")
    scan_config: dict[str, Any] = Field(description="The scan configuration (scan_config "
                                        "schema) the frames were acquired with")
    recording_id: str | None = Field(
        None, pattern=RECORDING_ID_PATTERN, description="Unique id of the recording (uuid4, "
        "32 hex digits), drawn when it is created (version 4; absent before)")
    created: str | None = Field(None, description="UTC creation time, ISO 8601")
    frames: int | None = Field(None, ge=0, description="Frames written (set when closed)")
    codec: str | None = Field(None, description="Codec of the frames array, informative")
    writer: str | None = Field(None, description="Program that wrote the recording")
    error: str | None = Field(None, description="Why the recording stopped, if it failed")
    frames_planned: int | None = Field(
        None, ge=0, description="Frames the live scan expected (its plan, camera.frames or the "
        "sender's count): a replay with fewer is 'incomplete'")
    fsync_s: float | None = Field(
        None, ge=0, description="The recorder made its data and metadata durable (fsync) at "
        "least this often, s: a power cut loses at most this much of the stream")
    motion_queue: MotionQueue | None = Field(
        None, description="The printer's motion queue over the scan (version 5): how the "
        "rows of the array 'trapq' map to the frames' time stamps and stage positions")


class RecordingError(ValueError):
    """A recording that cannot be replayed; the message names the array, attribute or frame."""


@dataclass
class RecordingReport:
    """What :func:`open_recording` (and the frame iterator) found in a recording."""

    path: str
    status: str
    entries: int = 0  # entries of the per-frame arrays examined
    frames: int = 0  # usable frames (replayed)
    unwritten: int = 0  # trailing entries never written (array growth, or a crash)
    first_id: int | None = None
    last_id: int | None = None
    duration_s: float = 0.0
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (first missing id, count)
    duplicates: list[int] = field(default_factory=list)  # ids seen again (copies dropped)
    out_of_order: list[int] = field(default_factory=list)  # frame ids stored out of order (sorted)
    missing_metadata: list[int] = field(default_factory=list)  # array indexes without metadata
    missing_chunks: list[int] = field(default_factory=list)  # frame ids without a frame chunk
    corrupt: list[int] = field(default_factory=list)  # frame ids whose chunk cannot be decoded
    #: frame ids whose pixels are not the ones their header copy's digest names (v4)
    misplaced: list[int] = field(default_factory=list)
    time_backwards: list[int] = field(default_factory=list)  # frame ids: time stamp went back
    time_jumps: list[int] = field(default_factory=list)  # frame ids: implausible time step
    #: of those, frame ids left out: no stage position, so placed by the wrong time stamp
    time_left_out: list[int] = field(default_factory=list)
    #: entries the arrays' zarr.json claim, when the chunk files present hold fewer
    claimed_entries: int | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def lost(self) -> int:
        return sum(n for _, n in self.gaps)

    @property
    def defects(self) -> int:
        return (len(self.gaps) + len(self.duplicates) + len(self.out_of_order)
                + len(self.missing_metadata) + len(self.missing_chunks) + len(self.corrupt)
                + len(self.misplaced) + len(self.time_backwards) + len(self.time_jumps)
                + (self.claimed_entries is not None))

    def lines(self) -> list[str]:
        """The report as text, one finding per line (ids listed up to 20)."""
        out = [f"recording   {self.path} (status {self.status})",
               f"frames      {self.frames} usable of {self.entries} entries"
               + (f", {self.unwritten} trailing entries not written" if self.unwritten else "")]
        if self.first_id is not None:
            out.append(f"frame_id    {self.first_id}..{self.last_id}, {self.duration_s:.3f} s")
        if self.gaps:
            out.append(f"gaps        {len(self.gaps)} ({self.lost} frames lost): "
                       + _ids([f"{a}..{a + n - 1}" if n > 1 else str(a) for a, n in self.gaps]))
        for name, ids in (("duplicates", self.duplicates), ("out of order", self.out_of_order),
                          ("no metadata", self.missing_metadata),
                          ("no chunk", self.missing_chunks), ("corrupt", self.corrupt),
                          ("misplaced", self.misplaced),
                          ("time back", self.time_backwards),
                          ("time jump", self.time_jumps)):
            if ids:
                what = "array indexes" if name == "no metadata" else "frame_id"
                out.append(f"{name:<11} {len(ids)}: {what} " + _ids([str(i) for i in ids]))
        out += [f"note        {n}" for n in self.notes]
        return out

    def as_dict(self) -> dict[str, Any]:
        """A JSON-able summary, stored in the attributes of a mosaic replayed from it."""
        return {"path": self.path, "status": self.status, "frames": self.frames,
                "entries": self.entries,
                "frames_lost": (self.lost + len(self.corrupt) + len(self.misplaced)
                                + len(self.time_left_out)),
                "gaps": [list(g) for g in self.gaps[:100]], "duplicates": self.duplicates[:100],
                "out_of_order": self.out_of_order[:100],
                "missing_metadata": self.missing_metadata[:100],
                "missing_chunks": self.missing_chunks[:100], "corrupt": self.corrupt[:100],
                "misplaced": self.misplaced[:100], "time_backwards": self.time_backwards[:100],
                "time_jumps": self.time_jumps[:100],
                "time_left_out": self.time_left_out[:100]}


def _ids(ids: list[str], limit: int = 20) -> str:
    more = f" ... (+{len(ids) - limit})" if len(ids) > limit else ""
    return ", ".join(ids[:limit]) + more


def _array(group: zarr.Group, name: str, path: str) -> zarr.Array | None:
    try:
        node = group.get(name)
    except Exception as exc:  # noqa: BLE001 - a corrupt or truncated zarr.json of the array
        raise RecordingError(f"{path}/{name}/zarr.json: unreadable array metadata "
                             f"({type(exc).__name__}: {exc})") from None
    if node is None:
        return None
    if not isinstance(node, zarr.Array):
        raise RecordingError(f"{path}: '{name}' is not an array")
    return node


def _chunk_keys(arr: zarr.Array) -> set[str]:
    """Keys (relative to the array) of the chunks present in the store."""
    from zarr.core.sync import sync

    sp = arr.store_path
    prefix = f"{sp.path}/" if sp.path else ""

    async def _list() -> list[str]:
        return [k async for k in sp.store.list_prefix(prefix)]

    return {k[len(prefix):] for k in sync(_list())}


def _first_index(arr: zarr.Array, key: str) -> int | None:
    """First chunk index of a chunk key of ``arr`` (zarr's default chunk key encoding,
    ``c/i/…`` in versions 1 and 2, ``c.i.…`` in version 3, as the array's metadata says);
    None for anything else (``zarr.json``, a temporary file a crash left)."""
    sep = getattr(arr.metadata.chunk_key_encoding, "separator", "/")  # type: ignore[union-attr]
    parts = key.split(sep)
    if len(parts) == arr.ndim + 1 and parts[0] == "c" and all(p.isdigit() for p in parts[1:]):
        return int(parts[1])
    return None


def _first_indexes(arr: zarr.Array, keys: set[str]) -> set[int]:
    """First chunk index of each chunk key of ``arr`` (:func:`_first_index`)."""
    return {i for i in (_first_index(arr, k) for k in keys) if i is not None}


def chunk_keys_from(arr: zarr.Array, first: int) -> list[str]:
    """Keys (relative to the array) of the stored chunks of ``arr`` whose first chunk index
    is ``first`` or more, either key encoding."""
    return [k for k in _chunk_keys(arr) if (i := _first_index(arr, k)) is not None
            and i >= first]


def _stored(arr: zarr.Array) -> tuple[int, ...]:
    """Shape of one stored object of ``arr`` (its shard if sharded, else its chunk)."""
    return tuple(int(c) for c in (arr.shards or arr.chunks))


def header_row(h: FrameHeader, *, index: int | None = None,
               digest: int | None = None) -> np.ndarray:
    """The ``headers`` row of a frame header (positions as the bits of float64): 6 columns,
    or 8 with the frame's array ``index`` and pixel ``digest`` (version 4)."""
    pos = np.array([np.nan if h.stage_x_um is None else h.stage_x_um,
                    np.nan if h.stage_y_um is None else h.stage_y_um], np.float64)
    bits = pos.view(np.int64)
    row = [h.frame_id, h.timestamp_ns, h.focus_index, bits[0], bits[1], h.pass_index]
    if index is not None and digest is not None:
        row += [index, digest]
    return np.array(row, np.int64)


def read_recording_id(path: str | Path) -> str | None:
    """The ``recording_id`` attribute of the recording at ``path`` (None for a recording
    made before version 4, or for anything that is not a readable group)."""
    try:
        value = zarr.open_group(str(path), mode="r").attrs.get("recording_id")
    except Exception:  # noqa: BLE001 - not a readable Zarr group: no id
        return None
    return value if isinstance(value, str) else None


def annotate_mosaic(path: str | Path, rec: Recording) -> None:
    """Record in a mosaic's attributes which recording it was replayed from."""
    from sffscan.pipeline.mosaic.attrs import MosaicAttrs

    group = zarr.open_group(str(path), mode="r+")
    attrs = MosaicAttrs.model_validate({**group.attrs.asdict(),
                                        "recording": rec.report.as_dict()})
    group.update_attributes(attrs.model_dump(mode="json"))
