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

Motion along -x is handled by mirroring: internally columns are numbered so that they
always complete in increasing order. The columns' geometry is
:mod:`sffscan.stages.volume_columns`'s; the blocks' reduction (with each block's height
uncertainty) :mod:`sffscan.stages.volume_reduce`'s.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from sffscan.stages.accumulate import AccumulatorState, Write, apply_writes
from sffscan.stages.bands import BandWorkers, row_bands
from sffscan.stages.depth import DEPTH_METHODS
from sffscan.stages.depth_harmonics import STREAMING_METHODS, harmonic_table
from sffscan.stages.depth_statistics import SHAPE_SAMPLE_STEP
from sffscan.stages.volume_columns import block_ranges, final_end, volume_geometry
from sffscan.stages.volume_reduce import BlockResult, BlockSource, reduce_block
from sffscan.stages.volume_tasks import grid_rows, keeps_grid, pieces, run_task, scratch_arrays


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

    def _advance(self, force_to: int | None = None) -> list[tuple[int, int]]:
        """Ranges of columns whose own state and halo are final."""
        assert self.next_u is not None
        # columns [next_u, final_end) are complete or dead
        stop = final_end(self.count, self.next_u, self.end_u, ring=self.ring,
                         n_levels=self.n, dead_below=self.dead_below) - self.halo
        if force_to is not None:
            stop = max(stop, min(force_to, self.end_u))
        return self._take_blocks(stop, partial=force_to is not None)

    def finish(self) -> list[BlockResult]:
        """Reduce every remaining column (end of pass or stream)."""
        self._apply_pending()
        return [self.reduce(*r) for r in self.flush()]

    def flush(self) -> list[tuple[int, int]]:
        """Ranges of all remaining columns, final now."""
        return [] if self.next_u is None else self._take_blocks(self.end_u, partial=True)

    def _take_blocks(self, stop: int, *, partial: bool) -> list[tuple[int, int]]:
        """The blocks of columns [next_u, stop)
        (:func:`~sffscan.stages.volume_columns.block_ranges`); next_u moves past them."""
        assert self.next_u is not None
        out = block_ranges(self.next_u, stop, self.block, partial=partial)
        if out:
            self.next_u = out[-1][1]
        return out

    def reduce(self, u0: int, u1: int) -> BlockResult:
        """Depth of internal columns [u0, u1), then release the columns left behind
        (:func:`sffscan.stages.volume_reduce.reduce_block`, which says what it returns)."""
        assert self.y0 is not None
        self._apply_pending()
        block = reduce_block(self._block_source(self.y0), u0, u1)
        self._release(u0 - self.halo)
        return block

    def _block_source(self, y0: int) -> BlockSource:
        """What :func:`~sffscan.stages.volume_reduce.reduce_block` reads of this volume."""
        return BlockSource(
            count=self.count, row_lo=self.row_lo, row_hi=self.row_hi, argmax=self.argmax,
            tex=self.tex, fv=self.fv, grid=self.grid, arrays=self.arrays,
            run_task=self._run_task, heights=self.heights, n=self.n, rows=self.rows,
            ring=self.ring, halo=self.halo, first_u=self.first_u, end_u=self.end_u, y0=y0,
            direction=self.direction, method=self.method, median_size=self.median_size,
            spread_size=self.spread_size, uncertainty=self.uncertainty,
            window_test=self.window_test)

    def _run_task(self, task: str, params: dict[str, object]) -> None:
        """Band task ``task`` (:mod:`sffscan.stages.volume_tasks`) on :attr:`arrays`, by the
        band threads where there are some (else on all rows, in the caller's thread)."""
        def band(r0: int, r1: int) -> None:
            run_task(self.arrays, task, params, (r0, r1))
        if isinstance(self.workers, BandWorkers) and len(self._bands) > 1:
            self.workers.run(band, self._bands)
        else:
            band(0, self.rows)

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
