"""Raw-stream recorder: tees the source's frames into a recording while the scan runs.

:class:`RecordingWriter` writes the layout of :mod:`sffscan.pipeline.formats.recording`; the sink
(:func:`recorder_sink`) taps the ``source`` stage through its own blocking queue, so no
frame is ever skipped: if the disk is slower than the camera, the pipeline waits, and
that is reported loudly (a logged warning while it happens, the recorder's busy share
and the pipeline's waiting time in the summary).

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
import errno
import logging
import time
import uuid
from collections.abc import Iterator
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
from sffscan.stages.protocol import FullPolicy, Sink, Tapped
from zarr.codecs import BloscCodec, BloscShuffle, Crc32cCodec
from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding

log = logging.getLogger(__name__)

#: the recorder makes what it wrote durable (fsync) at least this often, s
FSYNC_S = 1.0
#: default codec of the frames array (see bench/recorder_results.md)
DEFAULT_CODEC = "blosc-lz4"
#: chunk key separator of the frames and headers arrays -> the recording's format version
KEY_SEPARATORS = {".": 4, "/": 2}
#: the recorder's queue holds up to this many bytes of frames (within 16..1024 frames)
QUEUE_BYTES = 512 * 2**20


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


class RecorderError(OSError):
    """The recording cannot be written (disk full, path unusable); the message says what
    was kept."""


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
        slower than the stream past it: :class:`RecorderSink`)."""
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


class RecorderSink(Sink):
    """Tees the ``source`` stage's frames into a :class:`RecordingWriter`.

    While the recorder is busy more than ``behind_share`` of the time (over windows of
    ``window_s``) it is the bottleneck: a warning is logged (at most every 5 s) and the
    summary says it fell behind; the runtime adds ``pipeline_waited_s``, the time the
    pipeline waited for it. If in such a window more than :attr:`DISK_SHARE` of its busy
    time went to waiting for the disk past the page cache
    (:mod:`~sffscan.pipeline.formats.unbuffered`), the rest of the recording goes through
    the cache (:meth:`RecordingWriter.use_page_cache`), which can hold a short scan's frames
    while a slow disk catches up; where the recorder's own CPU holds it back, nothing
    changes (the cache's copy would cost more CPU).
    """

    #: the share of a behind window's busy time spent waiting for the disk past the page
    #: cache above which the disk, not the recorder's CPU, is what holds it back
    DISK_SHARE = 0.5

    name = "recorder"
    taps = ("source",)
    policy = FullPolicy.BLOCK
    unit = "frames"

    def __init__(self, writer: RecordingWriter, *, fps: float, capacity: int,
                 behind_share: float = 0.9, window_s: float = 2.0) -> None:
        self.writer = writer
        self.fps = fps
        self.capacity = capacity
        self.behind_share = behind_share
        self.window_s = window_s
        self.busy_s = 0.0
        self.t_first: float | None = None
        self._win = (0.0, 0.0, 0)  # window start, busy in window, frames in window
        self._wait0 = 0.0  # the writer's disk wait past the cache at the window's start
        self.behind_windows = 0
        self.worst_fps: float | None = None
        self._warned_at = -1e9
        self.finished = False
        self.error: str | None = None

    def process(self, item: Any) -> Iterator[None]:
        if not isinstance(item, Tapped) or not isinstance(item.item, Frame):
            return iter(())
        t0 = time.perf_counter()
        if self.t_first is None:
            self.t_first = t0
            self._win = (t0, 0.0, 0)
            self._wait0 = self._disk_wait()
        try:
            self.writer.write(item.item)
        except OSError as exc:
            raise self._error(exc, item.item.header.frame_id) from exc
        dt = time.perf_counter() - t0
        self.busy_s += dt
        self._watch(t0 + dt, dt)
        return iter(())

    def _disk_wait(self) -> float:
        u = self.writer.unbuffered
        return u.wait_s if u is not None else 0.0

    def _watch(self, now: float, dt: float) -> None:
        start, busy, n = self._win
        busy, n = busy + dt, n + 1
        span = now - start
        if span < self.window_s:
            self._win = (start, busy, n)
            return
        self._win = (now, 0.0, 0)
        wait = self._disk_wait()
        waited, self._wait0 = wait - self._wait0, wait
        if busy / span < self.behind_share:
            return
        w = self.writer
        if w.unbuffered is not None and w.page_cache_from is None \
                and waited > self.DISK_SHARE * busy:
            w.use_page_cache()
            log.warning("the recorder waited for the disk %.0f %% of its busy time writing "
                        "past the page cache; from frame %d on it writes through the cache",
                        100 * waited / busy, w.page_cache_from)
        self.behind_windows += 1
        rate = n / busy if busy > 0 else 0.0
        self.worst_fps = rate if self.worst_fps is None else min(self.worst_fps, rate)
        if now - self._warned_at >= 5.0:
            self._warned_at = now
            mb = rate * self.writer.shape[0] * self.writer.shape[1] * self.writer.dtype.itemsize
            log.warning("the recorder is falling behind: busy %.0f %% of the last %.1f s, "
                        "writing %.0f frames/s (%.0f MB/s; the camera makes %g); the pipeline "
                        "waits for it", 100 * busy / span, span, rate, mb / 1e6, self.fps)

    def _error(self, exc: OSError, frame_id: int) -> RecorderError:
        w = self.writer
        what = "disk full" if exc.errno == errno.ENOSPC else f"write failed ({exc})"
        self.error = f"{what} at frame_id {frame_id}"
        kept = (f"keeps the {w.count} frame(s) written before it (frame_id {w.first_id}.."
                f"{w.last_id}), readable with 'sffscan info {w.path}'" if w.count else
                "holds no frame")
        err = RecorderError(f"recording {w.path}: {what} at frame_id {frame_id}; the scan "
                            f"stops. The recording {kept}")
        err.errno = exc.errno
        return err

    def finish(self) -> Iterator[None]:
        try:
            self.writer.close(status="complete")
        except OSError as exc:
            raise self._error(exc, self.writer.last_id or 0) from exc
        self.finished = True
        if self.behind_windows:
            log.warning("the recorder fell behind the stream in %d window(s) of %g s "
                        "(slowest %.0f frames/s against the camera's %g fps); see "
                        "'pipeline_waited_s' in the summary", self.behind_windows,
                        self.window_s, self.worst_fps, self.fps)
        return iter(())

    def close(self, *, failed: bool) -> None:
        if self.writer.closed:
            return
        # stopped early: keep what is written readable (metadata flushed, status 'failed')
        self.writer.close(status="failed",
                          error=self.error or "the scan stopped before the end of stream")

    def extra_stats(self) -> dict[str, Any]:
        w = self.writer
        mb = w.bytes / 1e6
        out: dict[str, Any] = {"frames_recorded": w.committed, "MB": round(mb, 1),
                               "MB/s (own busy time)": round(mb / self.busy_s, 1)
                               if self.busy_s else 0.0}
        if w.unbuffered is not None:  # frames written past the page cache, and refused
            out["frames_unbuffered"] = w.unbuffered.written
            if w.unbuffered.refused:
                out["frames_page_cache"] = w.unbuffered.refused
            if w.page_cache_from is not None:
                out["page_cache_from_frame"] = w.page_cache_from
        if self.behind_windows:
            out["FELL BEHIND"] = (f"in {self.behind_windows} window(s), slowest "
                                  f"{self.worst_fps:.0f} frames/s < {self.fps:g} fps")
        return out


def queue_capacity(cfg: ScanConfig) -> int:
    """Frames the recorder's queue holds: :data:`QUEUE_BYTES` worth, within 16..1024."""
    o = cfg.optics
    frame_bytes = o.height_px * o.width_px * np.dtype(o.dtype).itemsize
    return int(min(1024, max(16, QUEUE_BYTES // frame_bytes)))


def recorder_sink(cfg: ScanConfig, path: str, *, codec: str = DEFAULT_CODEC,
                  account: Any | None = None, page_cache: bool = False) -> Sink:
    """The sink that records the raw stream of a scan into ``path`` (``--record PATH``);
    ``account`` (the scan's :class:`~sffscan.pipeline.completeness.FrameAccount`) gives the
    recording's ``frames_planned``; ``page_cache`` as :class:`RecordingWriter`'s."""
    writer = RecordingWriter(path, cfg, codec=codec, account=account, page_cache=page_cache)
    return RecorderSink(writer, fps=cfg.optics.fps, capacity=queue_capacity(cfg))
