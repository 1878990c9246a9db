"""The pipeline's source stage: any frame iterator, every frame checked on the way in.

Sources (the simulated scanner, a replay, a camera) are plain iterators of
:class:`pipeline.messages.Frame`; this stage is what puts them at the head of a pipeline.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pipeline.messages import Frame, check_frame
from pipeline.runtime import Stage


class SourceStage(Stage):
    """Any frame iterator as the pipeline's source; every frame is checked on the way in.

    A frame of the wrong shape or dtype, a NaN frame or a focus index out of range stops
    the pipeline with an error naming the frame_id (:class:`pipeline.messages.FrameError`).
    """

    name = "source"

    def __init__(self, frames: Iterator[Frame], *, shape: tuple[int, int], dtype: str,
                 n_levels: int) -> None:
        self.frames = frames
        self.shape = shape
        self.dtype = np.dtype(dtype)
        self.n_levels = n_levels
        self.last_id = -1
        self.gaps = 0

    def produce(self) -> Iterator[Frame]:
        for frame in self.frames:
            check_frame(frame, shape=self.shape, dtype=self.dtype, n_levels=self.n_levels)
            fid = frame.header.frame_id
            if fid != self.last_id + 1 and self.last_id >= 0:
                self.gaps += 1
            self.last_id = fid
            yield frame

    def extra_stats(self) -> dict[str, int]:
        return {"frame_id_gaps": self.gaps}
