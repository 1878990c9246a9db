"""The pipeline's source stage: any frame iterator, every frame checked on the way in.

Sources (the simulated scanner, a replay, a camera) are plain iterators of
:class:`sffscan.stages.messages.Frame`; this stage is what puts them at the head of a pipeline.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
from sffscan.stages.messages import Frame, FrameError, check_frame
from sffscan.stages.protocol import Stage

__all__ = ["FrameBuffers", "SourceFrames", "SourceStage"]


class FrameBuffers:
    """Where a source that writes its frames' pixels itself (a replay's decoder, a camera's
    fetch, the simulator's render workers) puts them: new arrays, unless a runtime has
    bound an allocator.

    The process placement binds one that hands out slots of its shared-memory frame ring
    (:class:`sffscan.pipeline.channels.PooledSource`): a frame decoded there crosses the
    processes without the copy into the ring that a frame in a new array takes. A source
    offers its buffers by an attribute ``buffers`` of its frame iterator.
    """

    def __init__(self) -> None:
        self._alloc: Callable[[tuple[int, ...], np.dtype], np.ndarray] | None = None

    def bind(self, alloc: Callable[[tuple[int, ...], np.dtype], np.ndarray] | None) -> None:
        """Use ``alloc(shape, dtype)`` for the arrays from now on (None: new arrays again)."""
        self._alloc = alloc

    def empty(self, shape: tuple[int, ...], dtype: np.dtype | str) -> np.ndarray:
        """An array of ``shape`` and ``dtype`` for a frame's pixels (values undefined)."""
        dt = np.dtype(dtype)
        return np.empty(shape, dt) if self._alloc is None else self._alloc(shape, dt)


class SourceFrames(Iterator[Frame]):
    """A source's frames as an object: ``close()`` closes the iterator it wraps (a generator
    releases its file or device); ``buffers`` is the :class:`FrameBuffers` the source writes
    their pixels into (a replay's decoder, a camera's fetch, the simulator's render
    workers: what :attr:`SourceStage.buffers` finds), None for frames that arrive made (a
    message's bytes)."""

    def __init__(self, frames: Iterator[Frame], buffers: FrameBuffers | None = None, *,
                 lost_at_end: Callable[[], int] | None = None) -> None:
        self._frames = frames
        self.buffers = buffers
        #: frames the source knows it lost after the last one it gave (a camera whose
        #: frame_id jumped past the plan's end), read by :class:`SourceStage` when the
        #: frames end; None where a source cannot know
        self.lost_at_end = lost_at_end

    def __next__(self) -> Frame:
        return next(self._frames)

    def close(self) -> None:
        """Close the source (a generator's own close releases its file or device)."""
        close = getattr(self._frames, "close", None)
        if close is not None:
            close()


class SourceStage(Stage):
    """Any frame iterator as the pipeline's source; every frame is checked on the way in.

    Stops the pipeline with an error naming the frame_id
    (:class:`sffscan.stages.messages.FrameError`) for: a wrong shape or dtype, NaN pixels, values
    above the bit depth's full scale, a focus index out of range or out of step with the
    staircase ((frame_id - focus_index) mod N must stay constant), a frame_id that repeats
    or goes back, a pass index that goes back or exceeds the configured passes, and a stage
    position outside the planned scan area. Frame-id gaps (lost frames) are counted, and the
    frames a source knows it lost after its last one (``frames.lost_at_end``): their
    levels are missing, and the columns that needed them are marked invalid downstream.

    Parameters
    ----------
    frames : iterator of Frame
    shape : (int, int)
        Frame (height, width), px.
    dtype : str
        Frame dtype.
    n_levels : int
        Focus levels N.
    max_value : int
        Largest valid pixel value (255, or 1023 for 10-bit data in uint16).
    passes : int
        Configured number of passes.
    area_um : (x0, y0, x1, y1)
        Box the commanded stage positions must lie in, µm.
    buffers : FrameBuffers, optional
        Where a source that writes its frames' pixels itself (a replay) puts them; default
        the iterator's ``buffers`` attribute, if any.
    """

    name = "source"

    def __init__(self, frames: Iterator[Frame], *, shape: tuple[int, int], dtype: str,
                 n_levels: int, max_value: int, passes: int,
                 area_um: tuple[float, float, float, float],
                 buffers: FrameBuffers | None = None) -> None:
        self.frames = frames
        #: where the frames' pixels are written, for a source that writes them itself
        #: (``buffers``, else the iterator's own ``buffers`` attribute, if any)
        self.buffers: FrameBuffers | None = (buffers if buffers is not None
                                             else getattr(frames, "buffers", None))
        self.shape = shape
        self.dtype = np.dtype(dtype)
        self.n_levels = n_levels
        self.max_value = max_value
        self.passes = passes
        self.area_um = area_um
        self.last_id = -1
        self.last_pass = 0
        self.phase: int | None = None
        self.gaps = 0
        self.lost = 0

    def _check_header(self, frame: Frame) -> None:
        h = frame.header
        fid = h.frame_id
        if fid <= self.last_id:
            raise FrameError(f"frame_id {fid} arrives after frame_id {self.last_id}: "
                             "duplicated or out of order")
        if self.last_id >= 0 and fid != self.last_id + 1:
            self.gaps += 1
            self.lost += fid - self.last_id - 1
        if not self.last_pass <= h.pass_index < self.passes:
            raise FrameError(f"frame_id {fid}: pass_index {h.pass_index} after pass "
                             f"{self.last_pass} (configured passes: {self.passes})")
        phase = (fid - h.focus_index) % self.n_levels
        if self.phase is None:
            self.phase = phase
        elif phase != self.phase:
            raise FrameError(f"frame_id {fid}: focus_index {h.focus_index} is out of step with "
                             f"the staircase (expected {(fid - self.phase) % self.n_levels})")
        x0, y0, x1, y1 = self.area_um
        for name, v, lo, hi in (("stage_x_um", h.stage_x_um, x0, x1),
                                ("stage_y_um", h.stage_y_um, y0, y1)):
            if v is not None and not lo <= v <= hi:
                raise FrameError(f"frame_id {fid}: {name} = {v:g} µm lies outside the planned "
                                 f"scan area [{lo:g}, {hi:g}] µm")
        self.last_id, self.last_pass = fid, h.pass_index

    def produce(self) -> Iterator[Frame]:
        for frame in self.frames:
            check_frame(frame, shape=self.shape, dtype=self.dtype, n_levels=self.n_levels)
            if self.max_value < np.iinfo(self.dtype).max:
                top = int(frame.image.max())
                if top > self.max_value:
                    raise FrameError(f"frame_id {frame.header.frame_id}: pixel value {top} "
                                     f"exceeds the full scale {self.max_value} of the bit depth")
            self._check_header(frame)
            yield frame
        # frames lost after the last one (no later frame_id shows their gap), where the
        # source knows them (SourceFrames.lost_at_end)
        at_end = getattr(self.frames, "lost_at_end", None)
        tail = int(at_end()) if at_end is not None else 0
        if tail > 0:
            self.gaps += 1
            self.lost += tail

    def close(self, *, failed: bool) -> None:
        close = getattr(self.frames, "close", None)  # a generator releases its device/socket
        if close is not None:
            close()

    def extra_stats(self) -> dict[str, int]:
        return {"frame_id_gaps": self.gaps, "frames_lost": self.lost}
