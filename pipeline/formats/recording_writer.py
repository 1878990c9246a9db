"""Raw-stream recorder: tees the source's frames into a recording while the scan runs.

:class:`RecordingWriter` writes the layout of :mod:`sffscan.pipeline.formats.recording`; the sink
(:func:`~sffscan.pipeline.formats.recorder_sink.recorder_sink`) feeds it from the ``source``
stage.

Crash safety: each frame is one chunk, written when it arrives; the per-frame metadata is
buffered and written every ``flush_every`` frames, ``frame_id`` last, so an entry with a
``frame_id`` always has its frame and all its metadata. Zarr's local store replaces files
atomically (temporary file, then rename): a SIGKILL at any moment leaves every chunk either
as it was or as it is meant to be, and the reader replays up to the last flushed frame.
The arrays grow in steps of :data:`GROW` frames; the unwritten tail has ``frame_id`` -1.

Format version 2 (:mod:`sffscan.pipeline.formats.recording`): every chunk carries a CRC-32C,
and a copy of each frame's header is written beside the frame (array ``headers``) right
after its chunk, so a frame is readable as soon as its header copy is written, even before
the next metadata flush.

Format version 3: the same, with the chunks of ``frames`` and ``headers`` named with zarr's
default chunk key encoding and the separator ``.`` (``frames/c.i.0.0``, ``headers/c.i.0``,
all in the array's folder) rather than ``/`` (``frames/c/i/0/0``: two or three new folders
per frame, each created and fsynced). See ``bench/recorder_results.md``.

Format version 4 (written now): the same, with a ``recording_id`` (uuid4) in the attributes,
and each header copy holding the frame's array index and the digest of its pixels bound to
that index and to the id (:func:`~sffscan.pipeline.formats.recording_checks.frame_digest`,
CRC-32C, 0.16 ms per MB measured on the 2-core VM: 0.4 ms for a 2.6 MB frame): a
swapped or copied chunk file is found by the reader.

Durability: the files written are fsynced (and their folders) every ``fsync_s`` seconds
(default :data:`FSYNC_S`, 1 s) and at close: a power cut loses at most the last second of
the stream. A reserve file (:data:`sffscan.pipeline.formats.durable.RESERVE_BYTES`) is kept in the
recording while it is written and freed on close, so that after a disk-full error the
metadata and the status 'failed' can still be written; the error message names the frames
that are readable.
"""

from __future__ import annotations

import datetime as _dt
import time
import uuid
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zarr
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.formats.durable import SyncTracker, free_reserve, make_reserve
from sffscan.pipeline.formats.recording import (
    GROW,
    HEADER_COLUMNS,
    META_CHUNK,
    PER_FRAME,
    RecordingAttrs,
    chunk_keys_from,
    header_row,
)
from sffscan.pipeline.formats.recording_checks import frame_digest
from sffscan.pipeline.formats.unbuffered import UnbufferedFiles
from sffscan.pipeline.formats.zarr_chunks import Plans, write_many
from sffscan.stages.messages import Frame
from zarr.codecs import BloscCodec, BloscShuffle, Crc32cCodec
from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding

#: the recorder makes what it wrote durable (fsync) at least this often, s
FSYNC_S = 1.0
#: default codec of the frames array (see bench/recorder_results.md)
DEFAULT_CODEC = "blosc-lz4"
#: chunk key separator of the frames and headers arrays -> the recording's format version
KEY_SEPARATORS = {".": 4, "/": 2}


def frame_codecs(name: str) -> list[Any]:
    """Zarr v3 compressors for the frames array: ``blosc-lz4`` (byte shuffle),
    ``blosc-zstd`` (level 1), ``zstd`` (zarr's default, level 0) or ``none``."""
    if name == "blosc-lz4":
        return [BloscCodec(cname="lz4", clevel=5, shuffle=BloscShuffle.shuffle)]
    if name == "blosc-zstd":
        return [BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.shuffle)]
    if name == "zstd":
        from zarr.codecs import ZstdCodec

        return [ZstdCodec(level=0)]
    if name == "none":
        return []
    raise ValueError(f"unknown recording codec {name!r} (blosc-lz4, blosc-zstd, zstd, none)")


class RecordingWriter:
    """Writes a recording group: frames one chunk each, metadata in batches.

    Parameters
    ----------
    path : str or Path
        The recording's Zarr v3 group; must not exist (a recording is never overwritten).
    cfg : ScanConfig
        Stored in the attributes; gives the frame shape and dtype.
    codec : str
        See :func:`frame_codecs`.
    flush_every, flush_s : int, float
        Metadata is written every ``flush_every`` frames or ``flush_s`` seconds, whichever
        comes first (and at the end); the header copy beside each frame makes it readable
        before that.
    fsync_s : float
        Files written are made durable (fsync) at least this often, and at close.
    account : FrameAccount, optional
        The scan's frame account: its expected count goes to ``frames_planned`` at close.
    via_zarr : bool
        Write the chunks through zarr's own ``setitem`` rather than
        :func:`~sffscan.pipeline.formats.zarr_chunks.write_many` (the same files, about
        twice the CPU per frame; for the tests and the benchmark that compare the two).
    key_separator : {".", "/"}
        Separator of the chunk keys of ``frames`` and ``headers``: ``"."`` writes format
        version 4 (every chunk in the array's folder), ``"/"`` format version 2 (a folder
        per frame; for the tests and the benchmark that compare the two).
    recording_id : str, optional
        The recording's id (32 hex digits); default: a new uuid4 (tests that compare two
        recordings byte for byte give both the same).
    page_cache : bool
        Write the frames' chunks through the kernel's page cache (True) rather than past
        it (False, the default, where the file system allows it:
        :mod:`~sffscan.pipeline.formats.unbuffered`; the same files). The small header and
        metadata chunks always go through it.
    """

    def __init__(self, path: str | Path, cfg: ScanConfig, *, codec: str = DEFAULT_CODEC,
                 flush_every: int = 16, flush_s: float = 0.25, fsync_s: float = FSYNC_S,
                 account: Any | None = None, via_zarr: bool = False,
                 key_separator: Literal[".", "/"] = ".",
                 recording_id: str | None = None, page_cache: bool = False) -> None:
        self.path = Path(path)
        self.via_zarr = via_zarr
        if key_separator not in KEY_SEPARATORS:
            raise ValueError(f"key_separator {key_separator!r}: one of {list(KEY_SEPARATORS)}")
        self.key_separator = key_separator
        if self.path.exists():
            raise FileExistsError(f"{self.path}: exists; a recording is never overwritten, "
                                  "choose another path")
        o = cfg.optics
        self.shape = (o.height_px, o.width_px)
        self.dtype = np.dtype(o.dtype)
        self.codec = codec
        frame_codecs(codec)  # an unknown codec fails now, not at the first frame
        self.flush_every = max(1, flush_every)
        self.flush_s = flush_s
        self._flushed_at = 0.0
        self.attrs = RecordingAttrs(
            status="recording", frame_shape=self.shape, dtype=str(self.dtype),  # type: ignore[arg-type]
            scan_config=cfg.model_dump(mode="json"), codec=codec,
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), writer="sffscan",
            fsync_s=fsync_s, format_version=KEY_SEPARATORS[key_separator],
            recording_id=recording_id or uuid.uuid4().hex)
        self.account = account
        self.sync = SyncTracker(self.path, interval_s=fsync_s)
        self.group: zarr.Group | None = None
        self.capacity = 0
        self.plans = Plans()  # the arrays' chunk plans, worked out once
        self.page_cache = page_cache
        self.unbuffered = None if page_cache else UnbufferedFiles()
        self.page_cache_from: int | None = None  # frame index from which it took the cache
        self.count = 0  # frames whose chunk is written
        self.committed = 0  # frames whose metadata is written too
        self.bytes = 0
        self.first_id: int | None = None
        self.last_id: int | None = None
        self._pending: list[tuple[int, int, int, float, float, int]] = []
        self.closed = False

    def _open(self) -> zarr.Group:
        """Create the group at the first frame (a scan that fails to start leaves nothing)."""
        if self.group is not None:
            return self.group
        group = zarr.open_group(str(self.path), mode="w-")
        keys = DefaultChunkKeyEncoding(separator=self.key_separator)
        self.frames = group.create_array(
            name="frames", shape=(0, *self.shape), chunks=(1, *self.shape), dtype=self.dtype,
            fill_value=0, compressors=[*frame_codecs(self.codec), Crc32cCodec()],
            dimension_names=("frame", "y", "x"), chunk_key_encoding=keys,
            # a chunk equal to the fill value (an all-black frame) must be stored too: the
            # reader takes an absent chunk for a lost frame
            config={"write_empty_chunks": True})
        self.meta = {
            name: group.create_array(name=name, shape=(0,), chunks=(META_CHUNK,), dtype=dtype,
                                     fill_value=fill, compressors=[Crc32cCodec()],
                                     dimension_names=("frame",),
                                     config={"write_empty_chunks": True})
            for name, (dtype, fill, _) in PER_FRAME.items()
        }
        self.headers = group.create_array(
            name="headers", shape=(0, len(HEADER_COLUMNS)), chunks=(1, len(HEADER_COLUMNS)),
            dtype="int64", fill_value=-1, compressors=[Crc32cCodec()],
            dimension_names=("frame", "field"), config={"write_empty_chunks": True},
            chunk_key_encoding=keys,
            attributes={"columns": list(HEADER_COLUMNS)})
        group.update_attributes(self.attrs.model_dump(mode="json"))
        self.group = group
        make_reserve(self.path)
        self.sync.add(["zarr.json", "headers/zarr.json", "frames/zarr.json",
                       *(f"{name}/zarr.json" for name in PER_FRAME)])
        return group

    def _put(self, items: list[tuple[zarr.Array, Any, np.ndarray]]) -> None:
        """Write array regions, in this order."""
        if self.via_zarr:
            for arr, sel, value in items:
                arr[sel] = value
        else:
            write_many(items, plans=self.plans,
                       unbuffered=self.unbuffered if self.page_cache_from is None else None)

    def use_page_cache(self) -> None:
        """Write the frames from the next one on through the page cache (the disk is
        slower than the stream past it:
        :class:`~sffscan.pipeline.formats.recorder_sink.RecorderSink`)."""
        if self.unbuffered is not None and self.page_cache_from is None:
            self.page_cache_from = self.count
            self.unbuffered.close()

    def _grow(self, n: int) -> None:
        if n <= self.capacity:
            return
        cap = (n + GROW - 1) // GROW * GROW
        self.frames.resize((cap, *self.shape))
        self.headers.resize((cap, len(HEADER_COLUMNS)))
        for arr in self.meta.values():
            arr.resize((cap,))
        self.capacity = cap
        self.sync.add(["headers/zarr.json", "frames/zarr.json",
                       *(f"{name}/zarr.json" for name in PER_FRAME)])

    def write(self, frame: Frame) -> None:
        """Write one frame's chunk now; its metadata with the next flush."""
        h = frame.header
        image = frame.image
        if image.shape != self.shape or image.dtype != self.dtype:
            # never cast (70000 would wrap in uint16) nor reshape: the recording is evidence
            raise ValueError(f"recording {self.path}: frame_id {h.frame_id}: image dtype "
                             f"{image.dtype} shape {image.shape}, the configuration says "
                             f"{self.dtype} {self.shape} (optics.bit_depth, height_px, "
                             "width_px)")
        _check_ranges(h, self.path)
        self._open()
        self._grow(self.count + 1)
        i = self.count
        # chunk by chunk without zarr's event loop (the same files); two calls, so that the
        # header copy is written after the frame whatever path each takes: a header copy
        # means a whole frame
        self._put([(self.frames, i, image)])
        digest = frame_digest(image, index=i, recording_id=self.attrs.recording_id)
        self._put([(self.headers, i, header_row(h, index=i, digest=digest))])
        enc = self.frames.metadata.encode_chunk_key  # type: ignore[union-attr]
        self.sync.add([f"frames/{enc((i, 0, 0))}",
                       f"headers/{self.headers.metadata.encode_chunk_key((i, 0))}"])  # type: ignore[union-attr]
        self.count += 1
        self.bytes += frame.image.nbytes
        self.last_id = h.frame_id
        if self.first_id is None:
            self.first_id = h.frame_id
        nan = float("nan")
        self._pending.append((h.frame_id, h.timestamp_ns, h.focus_index,
                              nan if h.stage_x_um is None else h.stage_x_um,
                              nan if h.stage_y_um is None else h.stage_y_um, h.pass_index))
        now = time.perf_counter()
        if len(self._pending) >= self.flush_every or now - self._flushed_at >= self.flush_s:
            self.flush()
            self._flushed_at = now
        if self.sync.due():
            self.flush()
            self.sync.sync()

    def flush(self) -> None:
        """Write the pending metadata; ``frame_id`` last (it marks the entries complete)."""
        if not self._pending:
            return
        a, b = self.committed, self.committed + len(self._pending)
        cols = list(zip(*self._pending, strict=True))
        names = list(PER_FRAME)
        values = {name: (self.meta[name], slice(a, b), np.asarray(col, PER_FRAME[name][0]))
                  for name, col in zip(names, cols, strict=True)}
        self._put([v for name, v in values.items() if name != "frame_id"])
        self._put([values["frame_id"]])  # last, once the others are written
        self.sync.add([f"{name}/{self.meta[name].metadata.encode_chunk_key((c,))}"  # type: ignore[union-attr]
                       for name in names
                       for c in range(a // META_CHUNK, (b - 1) // META_CHUNK + 1)])
        self.committed = b
        self._pending.clear()

    def close(self, *, status: str = "complete", error: str | None = None) -> None:
        """Flush, trim the arrays to the frames written (when complete) and set the status."""
        if self.closed:
            return
        self.closed = True
        if self.unbuffered is not None:
            self.unbuffered.close()
        if self.group is None:  # no frame arrived: nothing to keep
            return
        free_reserve(self.path)  # room for the metadata and the status, even on a full disk
        failure: BaseException | None = None
        try:
            self.flush()
            if status == "complete":
                for arr in (self.frames, self.headers, *self.meta.values()):
                    _trim(arr, self.committed)
                self.sync.add(["headers/zarr.json", "frames/zarr.json",
                               *(f"{name}/zarr.json" for name in PER_FRAME)])
        except BaseException as exc:  # the status must still say that it did not complete
            failure = exc
            status, error = "failed", f"{error + '; ' if error else ''}closing: {exc}"
        planned = None
        if self.account is not None:
            planned = self.account.expected
            planned = planned if planned is not None else self.account.planned
        attrs = self.attrs.model_copy(update={"status": status, "frames": self.committed,
                                              "error": error, "frames_planned": planned})
        try:
            self.group.update_attributes(attrs.model_dump(mode="json"))
            self.attrs = attrs
            self.sync.add("zarr.json")
        except OSError:
            if failure is None:
                raise
            # the disk refuses even the status: it stays 'recording', which readers treat
            # as not complete; the first error is the one reported
        try:
            self.sync.sync()
        except OSError:
            if failure is None:
                raise
        if failure is not None:
            raise failure


def _check_ranges(h: Any, path: Path) -> None:
    """Each header field fits its stored type (a header built without validation, or from a
    source that bypassed it): a clear error naming the frame and the field, not numpy's
    OverflowError."""
    for name, (dtype, _, _) in PER_FRAME.items():
        value = getattr(h, name)
        if value is None or isinstance(value, float):
            continue
        info = np.iinfo(dtype)
        if not isinstance(value, int) or not 0 <= value <= info.max:
            raise ValueError(f"recording {path}: frame_id {h.frame_id}: field {name} = "
                             f"{value!r} is out of range (0..{info.max}, stored as {dtype})")


def _trim(arr: zarr.Array, n: int) -> None:
    """Shorten ``arr`` to ``n`` entries along its first axis, deleting the chunk files that
    lie beyond (as zarr's resize does, without asking the store for each of the up to
    :data:`GROW` chunks of the unwritten tail, which cost about 0.2 s of CPU at close)."""
    from zarr.core.sync import sync

    sync(arr.async_array.resize((n, *arr.shape[1:]), delete_outside_chunks=False))
    step = int(arr.chunks[0])
    folder = Path(arr.store_path.store.root) / arr.store_path.path  # type: ignore[attr-defined]
    for key in chunk_keys_from(arr, -(-n // step)):  # chunks wholly outside the new shape
        (folder / key).unlink()
