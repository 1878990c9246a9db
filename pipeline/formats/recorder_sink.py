"""The recorder's sink: the pipeline stage that tees the source's frames into a
:class:`~sffscan.pipeline.formats.recording_writer.RecordingWriter` while the scan runs.

The sink (:func:`recorder_sink`) taps the ``source`` stage through its own blocking queue,
so no frame is ever skipped: if the disk is slower than the camera, the pipeline waits, and
that is reported loudly (a logged warning while it happens, the recorder's busy share
and the pipeline's waiting time in the summary).
"""

from __future__ import annotations

import errno
import logging
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.formats.recording_writer import DEFAULT_CODEC, RecordingWriter
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import FullPolicy, Sink, Tapped

log = logging.getLogger(__name__)

#: the recorder's queue holds up to this many bytes of frames (within 16..1024 frames)
QUEUE_BYTES = 512 * 2**20


class RecorderError(OSError):
    """The recording cannot be written (disk full, path unusable); the message says what
    was kept."""


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
