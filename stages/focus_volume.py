"""Streaming focus volume in world coordinates: the accumulation of the depth stage
(:mod:`sffscan.stages.depth_stage`).

Because the lens staircase repeats, any N consecutive frames hold every focus level once:
a world column is complete as soon as it has been seen at all N levels, whatever stack
boundary it crossed. :class:`FocusVolume` keeps a ring buffer of the world columns that
are in view or waiting (a fixed number, so memory does not grow with the scan): each
frame's focus measure is added into the columns it covers, for each column and level
only the first observation (so a column's curve comes from N consecutive frames). Columns
are reduced to depth in blocks, in the order the motion completes them, once they and a
halo for the SPC median filter are complete, or can no longer be completed because they
left the view (those are returned invalid: NaN height, zero confidence, never filled in).

What a column keeps depends on the depth method. argmax, centroid, PC and SPC need only the
curve's sums (H_0, sum k y, Re and Im of the first harmonic,
:func:`sffscan.stages.depth_harmonics.harmonic_table`) and its argmax, so each frame is
*accumulated* into per-pixel sums and a running maximum as it arrives (a few passes of
OpenCV arithmetic, no N-level volume: 6 planes instead of N; SPC, PC and the argmax also
keep every level of every 16th row, the curves their block's departure bias is judged on).
The others (3-point fits, wcentroid, the adaptive ones) read the levels about a peak known
once a column and its neighbours are complete: the ring stores all their levels, and the
running argmax.

The frames' writes into this state may be held until the next block reduction (at most
``defer_writes`` of them; 1, applied at once, by default) and then applied together, strip
of rows by strip of rows, while each strip's state stays in cache
(:mod:`sffscan.stages.accumulate`): the same operations on every pixel in the same order,
so the blocks are those of writing each frame at once.

Every block also carries the height's uncertainty (µm, one sigma,
:mod:`sffscan.stages.depth_uncertainty`): from the block's depth (its scatter about its
local median) and each curve's width (its sums and its minimum: from the stored levels at
the reduction, or for the accumulating methods a running minimum kept like the maximum).

Motion along -x is handled by mirroring: internally columns are numbered so that they
always complete in increasing order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple, TypeVar

import numpy as np
from sffscan.stages import block_depth as blocks
from sffscan.stages.accumulate import AccumulatorState, Write, apply_writes
from sffscan.stages.bands import BandWorkers, row_bands
from sffscan.stages.depth import DEPTH_METHODS
from sffscan.stages.depth_choice import DEPARTURE_METHODS, wide_choice
from sffscan.stages.depth_harmonics import STREAMING_METHODS, harmonic_table
from sffscan.stages.depth_levels import levels_to_height
from sffscan.stages.depth_statistics import SHAPE_SAMPLE_STEP
from sffscan.stages.depth_window import WINDOW_STRIPS, window_choice
from sffscan.stages.volume_tasks import (
    gather,
    grid_rows,
    keeps_grid,
    pieces,
    run_task,
    scratch,
    scratch_arrays,
)

T = TypeVar("T")


def new_columns(x: int, prev_x: int | None, *, width: int, margin: int, direction: int,
                slack: int = 4) -> tuple[int, int]:
    """Frame columns [c0, c1) that can hold (column, level) pairs not yet seen.

    The focus volume keeps the first observation of each world column at each level. The
    previous frame at the same level (one staircase period earlier, at world x
    ``prev_x``) already covered the columns the two frames share, so only the columns
    beyond it along the motion can be new: the focus measure need not be computed for the
    others (about half of each frame at the default speed). ``slack`` px more are kept for
    registration corrections. Without a previous frame (start of a pass) every usable
    column is new.

    Parameters
    ----------
    x, prev_x : int or None
        World x of this frame and of the previous frame at the same level, px.
    width, margin : int
        Frame width and the border excluded on each side, px.
    direction : {+1, -1}
        Direction of the motion along x.
    """
    lo, hi = margin, width - margin
    if prev_x is not None:
        if direction == 1:
            lo = max(lo, prev_x + width - margin - x - slack)
        else:
            hi = min(hi, prev_x + margin - x + slack)
    return lo, max(lo, hi)


def volume_geometry(frame_shape: tuple[int, int], *, method: str, median_size: int,
                    spread_size: int, block_columns: int, row_slack: int, col_slack: int
                    ) -> tuple[int, int, int]:
    """A volume's halo of columns, its rows and its ring's columns (see :class:`FocusVolume`)."""
    # the median's reach (+1), and for "adaptive" the spread window's beyond it, so that a
    # block's filtered peaks and spreads equal those of the whole volume
    peak = method in ("adaptive", *blocks.BLOCK_CHOICES)
    halo = median_size // 2 + 1 + (spread_size // 2 if peak else 0)
    h, w = frame_shape
    return halo, h + 2 * row_slack, w + 2 * halo + 2 * block_columns + 2 * col_slack


class BlockResult(NamedTuple):
    """A reduced block of world columns (see :meth:`FocusVolume.reduce`)."""

    x0: int
    y0: int
    height_um: np.ndarray
    texture: np.ndarray
    confidence: np.ndarray
    complete: int
    uncertainty_um: np.ndarray | None
    bias_levels: float = 0.0
    """The bias the block's uncertainty holds (levels, ``b`` of
    :func:`sffscan.stages.depth_uncertainty.depth_uncertainty`: SPC's departure or a peak's
    centroid pull, one value for the block)."""


class FocusVolume:
    """Ring buffer of per-column focus curves (or their running sums) for one pass.

    Parameters
    ----------
    n_levels : int
        Focus levels N.
    frame_shape : (int, int)
        Frame (height, width), px.
    focus_heights_um : sequence of float
        Height in focus at each level, µm (length N).
    margin : int
        Frame border excluded on every side, px (focus-window half width + 1).
    direction : {+1, -1}
        Direction of the motion along x for this pass.
    method : str
        One of :data:`sffscan.stages.depth.DEPTH_METHODS` (the study's candidates read
        beyond a block's halo). Those of :data:`~sffscan.stages.depth.STREAMING_METHODS`
        accumulate sums and the argmax (``fv`` is None); the others store the N-level ring.
    median_size : int
        SPC median filter size; also sets the halo of columns kept around a block.
    spread_size : int
        Window over which ``"adaptive"`` measures the spread of the filtered peaks (the
        focus measure's window k, px); widens its halo by ``spread_size // 2``.
    block_columns : int
        Number of completed columns reduced at once.
    row_slack : int
        Rows allowed for across-motion wobble above and below the first frame, px.
    col_slack : int
        Columns kept beyond the frame's width in the ring, px.
    reuse : FocusVolume, optional
        A finished volume (the last pass's) of the same size whose N-level ring this one
        takes over instead of allocating its own.
    uncertainty : bool
        Compute each block's height uncertainty (a running minimum of every curve, and
        :func:`sffscan.stages.depth_uncertainty.height_uncertainty_um` per block); False
        (the benchmark's reference) leaves ``uncertainty_um`` None.
    defer_writes : int
        Frames' writes (column runs) held before they are applied (at the latest before
        each block reduction): applied together, strip by strip, the state stays in cache
        (:mod:`sffscan.stages.accumulate`; bit-identical for any value, 1 applies each
        frame at once, the default: 32 was slower end to end, commit 2d4ebc8).
        :meth:`add` keeps views of ``focus`` and ``image01`` until then: the caller must
        not change them.
    workers : BandWorkers, optional
        Band workers (:mod:`sffscan.stages.bands`): the accumulation and the reduction
        split by rows among their threads, each band read with the filters' reach; blocks
        bit-identical for any number. None: all in the caller's thread.
    """

    #: bytes of per-pixel state per strip of rows kept in cache while the deferred writes
    #: are applied (:func:`sffscan.stages.accumulate.apply_writes`)
    cache_bytes = 1 << 19

    def __init__(
        self,
        *,
        n_levels: int,
        frame_shape: tuple[int, int],
        focus_heights_um: Sequence[float],
        margin: int,
        direction: int = 1,
        method: str = "spc",
        median_size: int = 11,
        spread_size: int = 9,
        block_columns: int = 64,
        row_slack: int = 8,
        col_slack: int = 8,
        reuse: FocusVolume | None = None,
        uncertainty: bool = True,
        defer_writes: int = 1,
        workers: BandWorkers | None = None,
    ) -> None:
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction}")
        if method not in DEPTH_METHODS:
            raise ValueError(f"method must be one of {DEPTH_METHODS}, got {method!r}")
        self.n = n_levels
        self.h, self.w = frame_shape
        self.heights = np.asarray(focus_heights_um, dtype=np.float64)
        self.margin = margin
        self.direction = direction
        self.method = method
        self.uncertainty = uncertainty
        self.streaming = method in STREAMING_METHODS
        self.window_test = method == "shape_select"
        """Whether a block that does not take SPC is offered the 9-level centroid
        (:func:`sffscan.stages.depth_window.window_choice`): the default's rule since
        2026-12-05; False gives the rule before it (bench_depth_default.py's
        ``shape_select/no-window``)."""
        # the curves' minima: kept as frames arrive where no N-level ring holds the curves
        # (the ring's methods take them from the levels at the reduction)
        self.track_low = uncertainty and self.streaming
        # the curves a block's departure bias is judged on (every SHAPE_SAMPLE_STEP-th
        # row), kept where no N-level ring holds them: streaming SPC, PC and argmax
        self.track_grid = keeps_grid(method, streaming=self.streaming, uncertainty=uncertainty)
        self.median_size = median_size
        self.spread_size = spread_size
        self.halo, self.rows, self.ring = volume_geometry(
            frame_shape, method=method, median_size=median_size, spread_size=spread_size,
            block_columns=block_columns, row_slack=row_slack, col_slack=col_slack)
        self.block = block_columns
        self.row_slack = row_slack
        self.col_slack = col_slack
        self.fv: np.ndarray | None = None
        self.grid: np.ndarray | None = None
        self._init_state((self.rows, self.ring), reuse)
        if defer_writes < 1:
            raise ValueError(f"defer_writes must be >= 1, got {defer_writes}")
        self.defer_writes = defer_writes
        self.workers = workers
        self._bands = row_bands(0, self.rows, workers.k if workers is not None else 1)
        self._pending: list[Write] = []
        self._state = AccumulatorState(
            self.best, self.argmax, self.tex, self.sums, self.coef,
            self.low if self.track_low else None, self.fv, self._level_buf, self.grid,
            SHAPE_SAMPLE_STEP[0])
        self.y0: int | None = None  # world row of accumulator row 0
        self.next_u: int | None = None  # first internal column not yet reduced
        self.first_u = 0  # first internal column ever stored
        self.end_u = 0  # one past the last internal column stored
        self.dead_below = -(2**62)  # internal columns below this cannot be completed

    def _init_state(self, plane: tuple[int, int], reuse: FocusVolume | None) -> None:
        """The per-pixel state, in this process's own arrays, and the bookkeeping."""
        # filled now, so the pages are touched at start-up and not during the scan
        # the running argmax of every curve (all methods: the N-level methods reuse it)
        self.argmax = np.zeros(plane, np.uint8 if self.n <= 256 else np.uint16)
        self._level_buf = np.empty((self.rows, self.w), self.argmax.dtype)
        if self.streaming:
            # sums of harmonic_table(N) rows 0 (H_0), 2 (Re H_1), 3 (Im H_1), and 1 (sum k y)
            # for the centroid only; float32 (50 terms: ~1e-6 relative)
            self.sums = np.zeros((4 if self.method == "centroid" else 3, *plane), np.float32)
            self.coef = harmonic_table(self.n)[[0, 2, 3, 1]]
        else:
            # the confidence comes from the stored levels at the reduction (one read of a
            # block's N levels costs less than three running sums updated every frame)
            self.sums = np.zeros((0, *plane), np.float32)
            self.coef = np.zeros((0, self.n))
            if reuse is not None and reuse.fv is not None and reuse.fv.shape == (self.n, *plane):
                # the last pass's ring (its stale values are never read: see _release);
                # a new one would be allocated, touched and freed once per pass (325 MiB
                # at 1280 x 1024, N = 50: 0.68 s of CPU on the 2-core VM, measured); its
                # deferred writes first, so that none lands in the ring later
                reuse._apply_pending()
                self.fv = reuse.fv
            else:
                self.fv = np.empty((self.n, *plane), np.float32)
                self.fv.fill(0.0)
        if self.track_grid:  # like the ring, its stale values are never read
            shape = (self.n, grid_rows(plane[0]), plane[1])
            if reuse is not None and reuse.grid is not None and reuse.grid.shape == shape:
                reuse._apply_pending()
                self.grid = reuse.grid
            else:
                self.grid = np.zeros(shape, np.float32)
        self._init_bookkeeping()
        self.best = np.full((self.rows, self.ring), -1.0, np.float32)
        # the running minimum of every curve (its floor, for the curve's width)
        self.low = np.full(plane if self.track_low else (0, 0), np.inf, np.float32)
        self.tex = np.zeros((self.rows, self.ring), np.float32)
        #: the arrays the band tasks read and write (sffscan.stages.volume_tasks)
        self.arrays = {"best": self.best, "argmax": self.argmax, "tex": self.tex,
                       "sums": self.sums, "low": self.low, "heights": self.heights,
                       **({} if self.fv is None else {"fv": self.fv}),
                       **({} if self.grid is None else {"grid": self.grid}),
                       **scratch_arrays(self.rows, self.block)}

    def _init_bookkeeping(self) -> None:
        """Which (column, level) pairs are stored, and the rows each covers."""
        self.filled = np.zeros((self.n, self.ring), bool)
        self.count = np.zeros(self.ring, np.int32)
        self.row_lo = np.zeros((self.n, self.ring), np.int32)
        self.row_hi = np.zeros((self.n, self.ring), np.int32)

    # -- coordinates ----------------------------------------------------------------------
    def _to_internal(self, x: int) -> int:
        """Internal index of the frame's first column (after mirroring for -x)."""
        return x if self.direction == 1 else -x - self.w + 1

    # -- streaming ------------------------------------------------------------------------
    def add(self, focus: np.ndarray, image01: np.ndarray, *, x: int, y: int,
            level: int, col0: int = 0) -> list[BlockResult]:
        """Add one frame at world position (x, y) px; return the blocks it completed.

        Parameters
        ----------
        focus : ndarray, float32, (H, w)
            Focus measure of the frame's columns [col0, col0 + w) (all of them, or the
            ones :func:`new_columns` says can still be new).
        image01 : ndarray, float32, (H, w)
            The same columns of the frame scaled to 0..1 (for the all-in-focus texture).
        x, y : int
            World position of the frame's first pixel, px.
        level : int
            Focus level of the frame, 0..N-1.
        col0 : int
            Frame column of ``focus[:, 0]``.

        Returns
        -------
        list of BlockResult
            Reduced blocks, in the order the motion completed them (see :meth:`reduce`).
        """
        if self.direction == -1:
            focus, image01 = focus[:, ::-1], image01[:, ::-1]
            col0 = self.w - (col0 + focus.shape[1])
            # OpenCV takes positive strides only
            focus, image01 = np.ascontiguousarray(focus), np.ascontiguousarray(image01)
        return self._add(focus, image01, focus.shape[1], x=x, y=y, level=level, col0=col0)

    def _add(self, focus: np.ndarray | None, image01: np.ndarray | None, width: int, *,
             x: int, y: int, level: int, col0: int) -> list[BlockResult]:
        """:meth:`add` of a frame ``width`` columns wide whose values are ``focus`` and
        ``image01`` (mirrored already; None where a subclass's writes find them elsewhere)."""
        u_frame = self._to_internal(x)
        m = self.margin
        if self.y0 is None:
            self.y0 = y - self.row_slack
        if self.next_u is None:
            self.next_u = self.first_u = self.end_u = u_frame + m
        # rows of this frame inside the accumulator
        r0 = max(y - self.y0 + m, 0)
        r1 = min(y - self.y0 + self.h - m, self.rows)
        if r1 <= r0:
            raise ValueError(f"frame at world y = {y} px lies outside the rows of this pass "
                             f"({self.y0}..{self.y0 + self.rows} px)")
        fr0 = r0 - (y - self.y0)
        # columns: valid frame columns [m, w - m) that were given -> internal u_frame + j
        u_lo = max(u_frame + max(m, col0), self.next_u)
        u_hi = u_frame + min(self.w - m, col0 + width)
        # make room: columns that would not fit in the ring are given up (left the view)
        done: list[BlockResult] = []
        self.dead_below = max(self.dead_below, u_frame + m - self.col_slack)
        if u_frame + self.w - m - self.first_u > self.ring:
            force = u_frame + self.w - m - self.ring + self.block + 2 * self.halo
            self.dead_below = max(self.dead_below, force)
            done += [self.reduce(*r) for r in self._advance(force_to=force)]
            self._release(min(self.next_u - self.halo, self.end_u))
            if u_frame + self.w - m - self.first_u > self.ring:  # a jump past all stored
                done += [self.reduce(*r) for r in self.flush()]
                self._release(self.end_u)
                self.next_u = self.first_u = self.end_u = max(u_lo, self.end_u)
            u_lo = max(u_lo, self.next_u)
        if u_hi > u_lo:
            new = ~self.filled[level, np.arange(u_lo, u_hi) % self.ring]
            edges = np.flatnonzero(np.diff(np.concatenate(([0], new.view(np.int8), [0]))))
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                for v0, v1, s0 in self._pieces(u_lo + int(a), u_lo + int(b)):
                    self._write(level, v0, v1, s0, focus, image01, u_frame + col0, r0, r1,
                                fr0)
        done += [self.reduce(*r) for r in self._advance()]
        return done

    def _pieces(self, u0: int, u1: int) -> Iterator[tuple[int, int, int]]:
        """Split internal columns [u0, u1) into (v0, v1, first slot) runs contiguous in the
        ring, so that they are read and written as slices, not gathered."""
        return pieces(u0, u1, self.ring)

    def _write(self, level: int, v0: int, v1: int, s0: int, focus: np.ndarray | None,
               image01: np.ndarray | None, u_frame: int, r0: int, r1: int, fr0: int) -> None:
        """Store one frame's focus measure for columns [v0, v1) (ring slots from s0)."""
        cs = slice(s0, s0 + (v1 - v0))
        fc = slice(v0 - u_frame, v1 - u_frame)
        self.filled[level, cs] = True
        self.count[cs] += 1
        self.row_lo[level, cs] = r0
        self.row_hi[level, cs] = r1
        self._queue_write(level, focus, image01, fr0, fc, r0, r1, cs)
        self.end_u = max(self.end_u, v1)

    def _queue_write(self, level: int, focus: np.ndarray | None, image01: np.ndarray | None,
                     fr0: int, fc: slice, r0: int, r1: int, cs: slice) -> None:
        """Hold the write of ``focus[fr0:fr0 + r1 - r0, fc]`` into state rows [r0, r1) and
        ring slots ``cs`` (applied once ``defer_writes`` are held)."""
        assert focus is not None and image01 is not None
        fr = slice(fr0, fr0 + (r1 - r0))
        fm = focus[fr, fc]
        if fm.strides[1] != 4:
            fm = np.ascontiguousarray(fm, dtype=np.float32)
        self._pending.append(Write(level, fm, image01[fr, fc], r0, r1, cs))
        if len(self._pending) >= self.defer_writes:
            self._apply_pending()

    def _apply_pending(self) -> None:
        """Apply the writes deferred since the last reduction
        (:func:`sffscan.stages.accumulate.apply_writes`)."""
        if self._pending:
            if isinstance(self.workers, BandWorkers) and len(self._bands) > 1:
                pending = self._pending
                self.workers.run(lambda a, b: apply_writes(
                    self._state, pending, cache_bytes=self.cache_bytes, rows=(a, b)),
                    self._bands)
            else:
                apply_writes(self._state, self._pending, cache_bytes=self.cache_bytes)
            self._pending.clear()

    def _gather(self, arr: np.ndarray, u0: int, u1: int) -> np.ndarray:
        """``arr[..., columns u0..u1)`` from the ring: a view unless it wraps."""
        return gather(arr, u0, u1, self.ring)

    def _advance(self, force_to: int | None = None) -> list[tuple[int, int]]:
        """Ranges of columns whose own state and halo are final."""
        assert self.next_u is not None
        us = np.arange(self.next_u, self.end_u)
        final = (self.count[us % self.ring] == self.n) | (us < self.dead_below)
        open_ = np.flatnonzero(~final)
        final_end = self.next_u + (int(open_[0]) if open_.size else us.size)
        stop = final_end - self.halo  # columns [next_u, final_end) are complete or dead
        if force_to is not None:
            stop = max(stop, min(force_to, self.end_u))
        out = []
        while stop - self.next_u >= self.block or (force_to is not None and stop > self.next_u):
            u1 = min(self.next_u + self.block, stop)
            out.append((self.next_u, u1))
            self.next_u = u1
        return out

    def finish(self) -> list[BlockResult]:
        """Reduce every remaining column (end of pass or stream)."""
        self._apply_pending()
        return [self.reduce(*r) for r in self.flush()]

    def flush(self) -> list[tuple[int, int]]:
        """Ranges of all remaining columns, final now."""
        if self.next_u is None or self.next_u >= self.end_u:
            return []
        out = []
        while self.next_u < self.end_u:
            u1 = min(self.next_u + self.block, self.end_u)
            out.append((self.next_u, u1))
            self.next_u = u1
        return out

    def reduce(self, u0: int, u1: int) -> BlockResult:
        """Depth of internal columns [u0, u1), then release the columns left behind.

        Returns
        -------
        BlockResult
            ``x0``, ``y0``: world position of the block's first column and row, px;
            ``height_um``, ``texture``, ``confidence``: float32 (rows, u1 - u0), NaN height
            and texture and zero confidence where a pixel's curve lacks levels;
            ``complete``: columns seen at all N levels; ``uncertainty_um``: the height's
            uncertainty, µm, one sigma, NaN where invalid
            (:func:`sffscan.stages.depth_uncertainty.height_uncertainty_um`; the depth's
            scatter measured within the block, replicated at its edges).
        """
        assert self.y0 is not None
        self._apply_pending()
        complete = self._gather(self.count, u0, u1) == self.n  # columns seen at every level
        lo = self._gather(self.row_lo, u0, u1).max(axis=0)
        hi = self._gather(self.row_hi, u0, u1).min(axis=0)
        rows = np.arange(self.rows)[:, None]
        valid = complete[None, :] & (rows >= lo[None, :]) & (rows < hi[None, :])
        depth, conf, _, _, bias, locking = self._depth(u0, u1, valid)
        invalid = ~valid
        height = levels_to_height(depth, focus_heights_um=self.heights)  # float32, new
        np.copyto(height, np.float32(np.nan), where=invalid)
        unc: np.ndarray | None = None
        if self.uncertainty:
            # invalid pixels (curves that lack levels) take the block's mean depth, so
            # that their values do not count as scatter of their valid neighbours
            fill = float(depth[valid].mean()) if valid.any() else 0.0
            unc = self._uncertainty(depth, valid, fill, bias, locking)
            np.copyto(unc, np.nan, where=invalid)
        conf = np.where(valid, conf, 0.0).astype(np.float32, copy=False)
        tex = np.where(valid, self._gather(self.tex, u0, u1), np.nan).astype(np.float32,
                                                                               copy=False)
        self._release(u0 - self.halo)
        if self.direction == -1:
            height, tex, conf = height[:, ::-1], tex[:, ::-1], conf[:, ::-1]
            unc = None if unc is None else unc[:, ::-1]
        x0 = u0 if self.direction == 1 else -(u1 - 1)  # world x of the block's first column
        return BlockResult(x0, self.y0, height, tex, conf, int(complete.sum()), unc, bias)

    def _depth(self, u0: int, u1: int, valid: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Depth (levels) and confidence of columns [u0, u1), their curves' sums (H_0,
        Re H_1, Im H_1) and minima (views of the block's scratch arrays), and the bias the
        uncertainty adds (levels: SPC's where the block took it, a peak method's
        :func:`~sffscan.stages.block_depth.block_choice` or
        :func:`~sffscan.stages.block_depth.block_peak_bias`, ``"wcentroid"``'s
        :func:`~sffscan.stages.block_depth.block_departure_bias`; else 0.0) and the locking it adds
        where the scatter cannot show it (:func:`~sffscan.stages.block_depth.block_choice`'s;
        else 0.0): the method chosen
        once for the block on its ``valid`` pixels' curves (rows, u1 - u0), then
        :func:`sffscan.stages.volume_tasks.depth` on each band of rows."""
        method, bias, floor, locking = self.method, 0.0, None, 0.0
        own = method in blocks.OWN_LEVEL_METHODS or method in blocks.BLOCK_CHOICES
        if self.fv is not None and method in blocks.BLOCK_CHOICES:
            # one choice for the block, whatever its bands
            method, bias, floor, locking = blocks.block_choice(
                self._gather(self.fv, u0, u1), self._gather(self.argmax, u0, u1), valid,
                method=method, centre=lambda: self._centre(u0, u1))
        elif self.fv is not None and method == "adaptive" and self.uncertainty:
            bias = blocks.block_peak_bias(self._gather(self.fv, u0, u1),
                                          self._gather(self.argmax, u0, u1), valid)
        # the fallback's wide centroid judged on the whole block, whatever its bands
        wide_test = (self.fv is not None and self.method in blocks.BLOCK_CHOICES
                     and method not in blocks.SPC_BLOCKS)
        # and the default's 9-level centroid (depth_window), as a stack's
        window_test = wide_test and self.window_test
        self._run_task("depth", {
            "u0": u0, "u1": u1, "a0": max(u0 - self.halo, self.first_u),
            "a1": min(u1 + self.halo, self.end_u), "ring": self.ring, "rows": self.rows,
            "halo": self.halo, "own": own, "method": method, "n_levels": self.n,
            "median_size": self.median_size, "spread_size": self.spread_size,
            "uncertainty": self.uncertainty, "wide_test": wide_test,
            "window_test": window_test,
            # SPC's range guard (depth_floor): a list of two floats or None, as JSON takes
            # it to band processes (NaN written as null)
            "floor": None if floor is None else [None if math.isnan(v) else v for v in floor]})
        a, shape = self.arrays, (self.rows, u1 - u0)
        if wide_test:
            wide_choice(scratch(a, "b_depth", shape), scratch(a, "b_peak", shape),
                        step=SHAPE_SAMPLE_STEP, valid=valid)
        if window_test:
            hidden = window_choice(scratch(a, "b_depth", shape), scratch(a, "b_window", shape),
                                   valid=valid, strips=WINDOW_STRIPS)
            if hidden is not None:  # the centroid's bias, beside the fallback's
                bias = math.hypot(bias, hidden)
        # a wide window's pull into lopsided curves' longer flank, a truncated curve's near
        # an end of the range, the argmax's sub-level offset: judged on the ring's curves, or
        # a streaming scan's SPC, PC or argmax on the judged rows it keeps (the grid)
        curves = self.fv if self.fv is not None else self.grid
        if method in DEPARTURE_METHODS and self.uncertainty and curves is not None:
            bias = blocks.block_departure_bias(
                self._gather(curves, u0, u1), self._gather(self.argmax, u0, u1),
                scratch(a, "b_depth", shape), self._centre(u0, u1), valid,
                rows_sampled=self.fv is None)
        return (scratch(a, "b_depth", shape), scratch(a, "b_conf", shape),
                scratch(a, "b_sums", (3, *shape)), scratch(a, "b_low", shape), bias, locking)

    def _centre(self, u0: int, u1: int) -> np.ndarray:
        """The filtered argmax of columns [u0, u1) as the depth task takes it (the median
        over ``median_size`` px of the argmax with the halo's columns), at the pixels the
        block's choice judges (every ``SHAPE_SAMPLE_STEP``-th row and column)."""
        a0, a1 = max(u0 - self.halo, self.first_u), min(u1 + self.halo, self.end_u)
        return blocks.judged_centre(self._gather(self.argmax, a0, a1), self.median_size,
                                    block=(u0 - a0, u1 - a0))

    def _uncertainty(self, depth: np.ndarray, valid: np.ndarray, fill: float,
                     bias: float, locking: float) -> np.ndarray:
        """The block's height uncertainty, µm (a new array), its invalid pixels' depth
        taken as ``fill`` (:func:`sffscan.stages.volume_tasks.uncertainty` on each band,
        from the block's scratch arrays that :meth:`_depth` filled)."""
        a, shape = self.arrays, depth.shape
        np.copyto(scratch(a, "b_filled", shape), np.where(valid, depth, fill))
        np.copyto(scratch(a, "b_valid", shape), valid)
        self._run_task("uncertainty", {
            "rows": shape[0], "width": shape[1], "n_levels": self.n, "method": self.method,
            "window": self.spread_size, "bias": bias, "locking": locking})
        return scratch(a, "b_unc", shape).copy()

    def _run_task(self, task: str, params: dict[str, object]) -> None:
        """Band task ``task`` (:mod:`sffscan.stages.volume_tasks`) on :attr:`arrays`, by the
        band threads where there are some."""
        self._by_bands(lambda r0, r1: run_task(self.arrays, task, params, (r0, r1)))

    def _by_bands(self, fn: Callable[[int, int], T]) -> list[T]:
        """``fn`` on each band of rows (one band, all rows, without band workers)."""
        if not isinstance(self.workers, BandWorkers) or len(self._bands) < 2:
            return [fn(0, self.rows)]
        return self.workers.run(fn, self._bands)

    def _release(self, below: int) -> None:
        """Free ring slots of columns below ``below`` (they will not be read again).

        The focus values themselves are not cleared: a slot's levels are valid only once
        its ``filled`` flag is set again, and a pixel whose curve lacks a level is invalid.
        """
        if below <= self.first_u:
            return
        self._apply_pending()
        for v0, v1, s0 in self._pieces(self.first_u, below):
            cs = slice(s0, s0 + (v1 - v0))
            self.filled[:, cs] = False
            self.count[cs] = 0
            self.best[:, cs] = -1.0
            self.low[:, cs] = np.inf
            self.tex[:, cs] = 0.0
            self.sums[:, :, cs] = 0.0
            self.argmax[:, cs] = 0
        self.first_u = below

    @property
    def nbytes(self) -> int:
        """Bytes held by the per-pixel state (fixed for the life of the volume)."""
        planes = [self.best, self.low, self.tex, self.argmax, self.sums, self.fv, self.grid]
        return sum(a.nbytes for a in planes if a is not None)
