"""The depth stage: focus frames in, blocks of depth out, one :class:`FocusVolume` per pass.

The accumulation and the reduction to depth are :mod:`sffscan.stages.focus_volume`'s; this
module places frames in the pass they belong to, keeps the last pass's N-level ring for
the next, and counts the complete and incomplete columns.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

from sffscan.stages.bands import BandTasks, BandWorkers
from sffscan.stages.depth_harmonics import STREAMING_METHODS
from sffscan.stages.focus_volume import BlockResult, FocusVolume
from sffscan.stages.messages import DepthBlock, DepthBlockHeader, FocusFrame, FrameError
from sffscan.stages.protocol import Stage
from sffscan.stages.volume_tasks import Layout

__all__ = ["DepthStage"]


class DepthStage(Stage):
    """Accumulates focus frames per pass and emits completed blocks of depth.

    ``workers`` > 1 splits each frame's accumulation and each block's reduction by rows
    among that many band workers (:mod:`sffscan.stages.bands`); the blocks are
    bit-identical for every number. They are threads, or with ``band_processes`` (a
    factory taking the number and the shared arrays' layout, such as
    :class:`sffscan.pipeline.band_processes.BandProcesses`) processes, started by
    :meth:`prepare` in the process that runs the stage. The other parameters are
    :class:`~sffscan.stages.focus_volume.FocusVolume`'s.
    """

    name = "depth"

    def __init__(self, *, n_levels: int, frame_shape: tuple[int, int],
                 focus_heights_um: Sequence[float], margin: int, method: str = "spc",
                 median_size: int = 11, block_columns: int = 64,
                 directions: Sequence[int] = (1,), slack_px: int = 8,
                 spread_size: int = 9, workers: int = 1,
                 band_processes: Callable[[int, Layout], BandTasks] | None = None) -> None:
        self.kwargs = dict(n_levels=n_levels, frame_shape=frame_shape,
                           focus_heights_um=focus_heights_um, margin=margin, method=method,
                           median_size=median_size, spread_size=spread_size,
                           block_columns=block_columns,
                           row_slack=slack_px, col_slack=slack_px)
        self.directions = list(directions)
        # band workers (sffscan.stages.bands): made at the first frame, in the thread or
        # process that runs the stage
        self.workers = workers
        self.band_processes = band_processes
        self._bands: BandWorkers | BandTasks | None = None
        self.volume: FocusVolume | None = None
        self.spare: FocusVolume | None = None  # the last pass's, whose ring the next reuses
        self.pass_index: int | None = None
        self.complete_columns = 0
        self.incomplete_columns = 0

    def prepare(self) -> None:
        """The first pass's N-level ring (325 MiB at 1280 x 1024, N = 50), allocated and
        touched now rather than at the first frame (0.68 s of CPU on the 2-core VM); band
        processes started now too."""
        tasks = self._band_workers() if self.band_processes is not None else None
        if self.spare is None and self.kwargs["method"] not in STREAMING_METHODS:
            self.spare = FocusVolume(direction=self.directions[0], workers=tasks,
                                     **self.kwargs)  # type: ignore[arg-type]

    def _band_workers(self) -> BandWorkers | BandTasks | None:
        """The band workers (made once), None for one."""
        if self._bands is None and (self.workers > 1 or self.band_processes is not None):
            if self.band_processes is not None:
                layout = FocusVolume.shared_layout(**self.kwargs)  # type: ignore[arg-type]
                self._bands = self.band_processes(self.workers, layout)
            else:
                self._bands = BandWorkers(self.workers, name="depth-band")
        return self._bands

    def _direction(self, pass_index: int) -> int:
        return self.directions[pass_index % len(self.directions)]

    def _blocks(self, results: list[BlockResult]) -> Iterator[DepthBlock]:
        assert self.pass_index is not None
        for r in results:
            width = r.height_um.shape[1]
            self.complete_columns += r.complete
            self.incomplete_columns += width - r.complete
            hdr = DepthBlockHeader(x0_px=r.x0, y0_px=r.y0, width_px=width,
                                   height_px=r.height_um.shape[0], pass_index=self.pass_index,
                                   complete_columns=r.complete,
                                   incomplete_columns=width - r.complete)
            yield DepthBlock(hdr, r.height_um, r.texture, r.confidence, r.uncertainty_um)

    def process(self, item: FocusFrame) -> Iterator[DepthBlock]:
        hdr = item.placed.header
        if self.volume is None or hdr.pass_index != self.pass_index:
            yield from self.finish()
            self.pass_index = hdr.pass_index
            self.volume = FocusVolume(direction=self._direction(hdr.pass_index),
                                      reuse=self.spare, workers=self._band_workers(),
                                      **self.kwargs)  # type: ignore[arg-type]
            self.spare = None
        x, y = item.placed.offset_px
        try:
            results = self.volume.add(item.focus, item.image01, x=x, y=y,
                                      level=hdr.focus_index, col0=item.col0)
        except ValueError as err:
            raise FrameError(f"frame_id {hdr.frame_id}: {err}") from err
        yield from self._blocks(results)

    def finish(self) -> Iterator[DepthBlock]:
        if self.volume is not None:
            yield from self._blocks(self.volume.finish())
            self.spare, self.volume = self.volume, None

    def close(self, *, failed: bool) -> None:
        if self._bands is not None:
            self._bands.close()
            self._bands = None

    def extra_stats(self) -> dict[str, int]:
        return {"complete_columns": self.complete_columns,
                "incomplete_columns": self.incomplete_columns}
