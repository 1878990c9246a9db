"""The depth stage: focus frames in, blocks of depth out, one :class:`FocusVolume` per pass.

The accumulation and the reduction to depth are :mod:`sffscan.stages.focus_volume`'s; this
module places frames in the pass they belong to, keeps the last pass's N-level ring for
the next, and counts the complete and incomplete columns.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from sffscan.stages.bands import BAND_CPU_KEY, BandTasks, BandWorkers
from sffscan.stages.depth_harmonics import STREAMING_METHODS
from sffscan.stages.focus_volume import FocusVolume
from sffscan.stages.messages import (
    DepthBlock,
    DepthBlockHeader,
    FocusFrame,
    FrameError,
    PlacedFrame,
    RawColumns,
)
from sffscan.stages.protocol import Stage
from sffscan.stages.shared_volume import SharedFocusVolume
from sffscan.stages.volume_reduce import BlockResult

__all__ = ["DepthStage"]


class DepthStage(Stage):
    """Accumulates focus frames per pass and emits completed blocks of depth.

    ``workers`` > 1 splits each frame's accumulation and each block's reduction by rows
    among that many band workers (:mod:`sffscan.stages.bands`); the blocks are
    bit-identical for every number. They are threads of the volume
    (:class:`~sffscan.stages.bands.BandWorkers`), or with ``band_tasks`` workers that run
    the volume's band tasks on arrays of their own and measure the focus of their rows
    (:class:`~sffscan.stages.messages.RawColumns` in): processes
    (:class:`sffscan.pipeline.band_processes.BandProcesses`, started by :meth:`prepare` in
    the process that runs the stage) or threads
    (:class:`~sffscan.stages.bands.BandTaskThreads`), their arrays laid out by
    :meth:`SharedFocusVolume.shared_layout
    <sffscan.stages.shared_volume.SharedFocusVolume.shared_layout>` of the same
    parameters; ``workers`` is then unused. The other parameters are
    :class:`~sffscan.stages.focus_volume.FocusVolume`'s.
    """

    name = "depth"

    def __init__(self, *, n_levels: int, frame_shape: tuple[int, int],
                 focus_heights_um: Sequence[float], margin: int, method: str = "spc",
                 median_size: int = 11, block_columns: int = 64,
                 directions: Sequence[int] = (1,), slack_px: int = 8,
                 spread_size: int = 9, workers: int = 1,
                 band_tasks: BandTasks | None = None) -> None:
        self.kwargs = dict(n_levels=n_levels, frame_shape=frame_shape,
                           focus_heights_um=focus_heights_um, margin=margin, method=method,
                           median_size=median_size, spread_size=spread_size,
                           block_columns=block_columns,
                           row_slack=slack_px, col_slack=slack_px)
        self.directions = list(directions)
        # band workers (sffscan.stages.bands): made at the first frame, in the thread or
        # process that runs the stage
        self.workers = workers
        self.band_tasks = band_tasks
        self._bands: BandWorkers | BandTasks | None = band_tasks
        self.volume: FocusVolume | None = None
        self.spare: FocusVolume | None = None  # the last pass's, whose ring the next reuses
        self.pass_index: int | None = None
        self.complete_columns = 0
        self.incomplete_columns = 0

    def prepare(self) -> None:
        """The first pass's N-level ring (325 MiB at 1280 x 1024, N = 50), allocated and
        touched now rather than at the first frame (0.68 s of CPU on the 2-core VM); band
        processes started now too."""
        if self.band_tasks is not None:
            self.band_tasks.arrays  # noqa: B018 (started now, not at the first frame)
        if self.spare is None and self.kwargs["method"] not in STREAMING_METHODS:
            self.spare = self._new_volume(self.directions[0], None, None)

    def _band_workers(self) -> BandWorkers | BandTasks | None:
        """The band workers (made once), None for one."""
        if self._bands is None and self.workers > 1:
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

    def process(self, item: FocusFrame | RawColumns) -> Iterator[DepthBlock]:
        placed = item.placed
        yield from self._new_pass(placed)
        assert self.volume is not None
        x, y = placed.offset_px
        hdr = placed.header
        try:
            if isinstance(item, RawColumns):
                results = self._add_raw(item)
            else:
                results = self.volume.add(item.focus, item.image01, x=x, y=y,
                                          level=hdr.focus_index, col0=item.col0)
        except ValueError as err:
            raise FrameError(f"frame_id {hdr.frame_id}: {err}") from err
        yield from self._blocks(results)

    def _add_raw(self, item: RawColumns) -> list[BlockResult]:
        """A frame whose focus the band workers measure
        (:meth:`sffscan.stages.shared_volume.SharedFocusVolume.add_raw`)."""
        if not isinstance(self.volume, SharedFocusVolume):
            raise ValueError("a frame to measure (RawColumns) needs the depth stage's band "
                             "workers (band_tasks)")
        c0, c1, a0, a1 = item.columns
        x, y = item.placed.offset_px
        return self.volume.add_raw(item.placed.image[:, a0:a1], cols=(c0 - a0, c1 - a0),
                                   measure=item.measure, x=x, y=y,
                                   level=item.placed.header.focus_index, col0=c0)

    def _new_pass(self, placed: PlacedFrame) -> Iterator[DepthBlock]:
        """At a frame of a new pass: the last pass's remaining blocks, and a new volume."""
        hdr = placed.header
        if self.volume is None or hdr.pass_index != self.pass_index:
            yield from self.finish()
            self.pass_index = hdr.pass_index
            self.volume = self._new_volume(self._direction(hdr.pass_index), self.spare,
                                           self._band_workers())
            self.spare = None

    def _new_volume(self, direction: int, reuse: FocusVolume | None,
                    workers: BandWorkers | BandTasks | None) -> FocusVolume:
        """A pass's volume: in the band tasks' arrays where there are some."""
        if self.band_tasks is not None:
            return SharedFocusVolume(direction=direction, reuse=reuse, workers=self.band_tasks,
                                     **self.kwargs)
        return FocusVolume(direction=direction, reuse=reuse,
                           workers=workers if isinstance(workers, BandWorkers) else None,
                           **self.kwargs)  # type: ignore[arg-type]

    def finish(self) -> Iterator[DepthBlock]:
        if self.volume is not None:
            yield from self._blocks(self.volume.finish())
            self.spare, self.volume = self.volume, None

    def close(self, *, failed: bool) -> None:
        if self._bands is not None:
            self._bands.close()
            self._bands = None

    def extra_stats(self) -> dict[str, int | float]:
        out: dict[str, int | float] = {"complete_columns": self.complete_columns,
                                       "incomplete_columns": self.incomplete_columns}
        if self.band_tasks is not None:  # counted with the process's own CPU
            out[BAND_CPU_KEY] = round(self.band_tasks.helpers_cpu_s(), 3)
        return out
