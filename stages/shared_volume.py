"""The focus volume with its rows split among band workers that run tasks on its state.

:class:`SharedFocusVolume` is a :class:`~sffscan.stages.focus_volume.FocusVolume` whose
per-pixel state lives in the named arrays of a :class:`~sffscan.stages.bands.BandTasks`
(one shared-memory segment, :class:`sffscan.pipeline.band_processes.BandProcesses`, or
this process's memory, :class:`~sffscan.stages.bands.BandTaskThreads`),
laid out by :meth:`SharedFocusVolume.shared_layout`. The bookkeeping (which columns and
levels are stored, when a block is final) stays in the volume's process; the work on the
pixels goes to the bands as tasks (:mod:`sffscan.stages.volume_tasks`): each frame's
writes, each block's depth and uncertainty. A frame comes either as its focus measure
(:meth:`~SharedFocusVolume.add`, copied into the shared arrays: 0.6 ms a full-size frame on
the 2-core VM) or as its raw columns (:meth:`~SharedFocusVolume.add_raw`), whose focus
measure each band computes for the rows it writes, so that it is never gathered. The
blocks are bit-identical to :class:`~sffscan.stages.focus_volume.FocusVolume`'s for any
number of bands (``tests/pipeline/test_band_processes.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sffscan.stages.bands import BandTasks, row_bands
from sffscan.stages.depth_harmonics import STREAMING_METHODS, harmonic_table
from sffscan.stages.focus_volume import FocusVolume
from sffscan.stages.volume_columns import volume_geometry
from sffscan.stages.volume_reduce import BlockResult
from sffscan.stages.volume_tasks import RAW_SLOTS, Layout, keeps_grid, volume_layout

__all__ = ["SharedFocusVolume"]


class SharedFocusVolume(FocusVolume):
    """A focus volume whose state and work are shared with band processes.

    Parameters
    ----------
    workers : BandTasks, keyword-only
        The band processes; their arrays must be laid out by :meth:`shared_layout` with
        the same parameters.
    **kwargs
        :class:`~sffscan.stages.focus_volume.FocusVolume`'s other parameters
        (``defer_writes`` is not used: each frame's writes are one task).
    """

    def __init__(self, *, workers: BandTasks, **kwargs: Any) -> None:
        self.tasks = workers
        self._specs: list[list[int]] = []  # the frame's writes, as the tasks take them
        self._frame_shape = (0, 0)  # add's focus measure in the shared arrays
        self._measure: dict[str, object] | None = None  # add_raw's frame, being added
        # the raw slot add_raw fills next, and the ticket of the last task that read each
        self._slot = self._measure_slot = 0
        self._slot_ticket = [0] * RAW_SLOTS
        super().__init__(**kwargs)
        self.workers = None  # the base class's band threads: none
        self._bands = row_bands(0, self.rows, workers.k)

    @classmethod
    def shared_layout(cls, *, n_levels: int, frame_shape: tuple[int, int],
                      method: str = "spc", median_size: int = 11, spread_size: int = 9,
                      block_columns: int = 64, row_slack: int = 8, col_slack: int = 8,
                      uncertainty: bool = True, raw_dtype: str = "<u2",
                      **_other: object) -> Layout:
        """The arrays band processes share with a volume of these parameters
        (:func:`sffscan.stages.volume_tasks.volume_layout`; ``raw_dtype``: the raw
        frames' for :meth:`add_raw`); the constructor's other parameters are ignored."""
        _halo, rows, ring = volume_geometry(
            frame_shape, method=method, median_size=median_size, spread_size=spread_size,
            block_columns=block_columns, row_slack=row_slack, col_slack=col_slack)
        streaming = method in STREAMING_METHODS
        return volume_layout(n_levels=n_levels, rows=rows, ring=ring,
                             frame_shape=frame_shape, block_columns=block_columns,
                             n_sums=(4 if method == "centroid" else 3) if streaming else 0,
                             levels=not streaming, low=uncertainty and streaming,
                             grid=keeps_grid(method, streaming=streaming,
                                             uncertainty=uncertainty),
                             raw_dtype=raw_dtype)

    def _init_state(self, plane: tuple[int, int], reuse: FocusVolume | None) -> None:
        """The state in the band processes' arrays, set as a new volume's would be (the
        N-level ring taken over from ``reuse`` as it is: its stale values are never read)."""
        self.tasks.wait_tasks()  # nothing of another volume's still running on them
        a = self.arrays = self.tasks.arrays
        want = self.shared_layout(
            n_levels=self.n, frame_shape=(self.h, self.w), method=self.method,
            median_size=self.median_size, spread_size=self.spread_size,
            block_columns=self.block, row_slack=self.row_slack, col_slack=self.col_slack,
            uncertainty=self.uncertainty, raw_dtype=a["raw"].dtype.str if "raw" in a else "")
        if {k: (v.shape, v.dtype.str) for k, v in a.items()} != want:
            raise ValueError("the band processes' arrays were laid out for another focus "
                             "volume (SharedFocusVolume.shared_layout of these parameters)")
        if reuse is not None:
            reuse._apply_pending()
        self.fv = a.get("fv")
        if reuse is None and self.fv is not None:  # as a new ring is (FocusVolume)
            self.fv.fill(0.0)
        self.grid = a.get("grid")
        if reuse is None and self.grid is not None:
            self.grid.fill(0.0)
        self.argmax = a["argmax"]
        self.argmax.fill(0)
        self._level_buf = a["level_buf"]
        self.sums = a["sums"]
        self.sums.fill(0.0)
        self.coef = a["coef"]
        self.coef[:len(self.sums)] = harmonic_table(self.n)[[0, 2, 3, 1][:len(self.sums)]]
        a["heights"][:] = self.heights
        self.best = a["best"]
        self.best.fill(-1.0)
        self.low = a["low"]
        self.low.fill(np.inf)
        self.tex = a["tex"]
        self.tex.fill(0.0)
        self._init_bookkeeping()

    # -- frames in -------------------------------------------------------------------------
    def add(self, focus: np.ndarray, image01: np.ndarray, *, x: int, y: int,
            level: int, col0: int = 0) -> list[BlockResult]:
        """:meth:`FocusVolume.add <sffscan.stages.focus_volume.FocusVolume.add>`, the
        frame's focus measure copied into the shared arrays first."""
        if self.direction == -1:
            focus, image01 = focus[:, ::-1], image01[:, ::-1]
            col0 = self.w - (col0 + focus.shape[1])
        self._apply_pending()  # before the copy overwrites what they read
        h, w = focus.shape
        if image01.shape != focus.shape or h > self.h or w > self.w:
            raise ValueError(f"focus {focus.shape} and image01 {image01.shape} must have "
                             f"one shape within the frame's {(self.h, self.w)}")
        a = self.arrays
        np.copyto(a["focus"][:h, :w], focus, casting="same_kind")
        np.copyto(a["image01"][:h, :w], image01, casting="same_kind")
        self._frame_shape = (h, w)
        done = self._add(None, None, w, x=x, y=y, level=level, col0=col0)
        self._submit_pending()  # waited for by the next frame's copy, or a block
        return done

    def add_raw(self, raw: np.ndarray, *, cols: tuple[int, int], measure: dict[str, object],
                x: int, y: int, level: int, col0: int) -> list[BlockResult]:
        """:meth:`add` of a frame's raw columns, their focus measure computed by the band
        processes (each its band of rows, with the operator's reach: bit-identical to the
        whole frame's for GLVM and TENV) and applied at once, never gathered.

        Parameters
        ----------
        raw : (H, w) ndarray of uint8 or uint16
            The frame's columns that the focus measure reads (copied into the shared
            arrays: 0.13 ms a full-size frame).
        cols : (int, int)
            The columns of ``raw`` whose focus measure is added (frame columns ``col0``
            to ``col0 + cols[1] - cols[0]``).
        measure : dict, keyword-only
            :func:`~sffscan.stages.focus_measure.focus_measure_raw`'s ``max_value``,
            ``operator`` and ``window``.
        x, y, level, col0 : int, keyword-only
            As for :meth:`add`.
        """
        self._submit_pending()
        h, w = raw.shape
        slot = self._slot
        dst = self.arrays["raw"][slot]
        if h != self.h or w > self.w or raw.dtype != dst.dtype:
            raise ValueError(f"raw {raw.shape} {raw.dtype} must be (height {self.h}, width "
                             f"<= {self.w}) of {dst.dtype}")
        self.tasks.wait_tasks(self._slot_ticket[slot])  # the slot's last frame is measured
        np.copyto(dst[:h, :w], raw, casting="no")
        self._slot = (slot + 1) % RAW_SLOTS
        width = cols[1] - cols[0]
        if self.direction == -1:
            col0 = self.w - (col0 + width)
        self._measure = {**measure, "shape": [h, w], "cols": list(cols),
                         "flip": self.direction == -1, "slot": slot}
        self._measure_slot = slot
        try:
            # the frame's writes go to the bands without waiting for them (a block reduced
            # on the way waits, as does the next use of this slot)
            done = self._add(None, None, width, x=x, y=y, level=level, col0=col0)
            self._submit_pending()
        finally:
            self._measure = None
        return done

    def _queue_write(self, level: int, focus: np.ndarray | None, image01: np.ndarray | None,
                     fr0: int, fc: slice, r0: int, r1: int, cs: slice) -> None:
        self._specs.append([level, fr0, fc.start, r0, r1, cs.start, cs.stop])

    def _apply_pending(self) -> None:
        """The frame's writes, by the band processes (one task for all of them), and every
        task before them, done: the state may be read and written here after it."""
        self._submit_pending()
        self.tasks.wait_tasks()

    def _submit_pending(self) -> None:
        """The frame's writes submitted to the band processes (one task for all of them),
        not waited for: each band applies them in order, before any later task of its."""
        if not self._specs:
            return
        params = {"writes": self._specs, "cache_bytes": self.cache_bytes,
                  "low": self.track_low}
        if self._measure is not None:
            ticket = self.tasks.submit_task("measure_accumulate", {**self._measure, **params},
                                            self._bands)
            self._slot_ticket[self._measure_slot] = ticket
        else:
            self.tasks.submit_task("accumulate", {**params, "shape": list(self._frame_shape)},
                                   self._bands)
        self._specs = []  # a new list: band threads read the one submitted later

    # -- blocks out ------------------------------------------------------------------------
    def _run_task(self, task: str, params: dict[str, object]) -> None:
        """Band task ``task`` by the band processes, on their shared arrays."""
        self.tasks.run_task(task, params, self._bands)
