"""The focus volume's accumulation kernel: frames' focus values added to per-pixel state.

:class:`sffscan.stages.focus_volume.FocusVolume` keeps, for every pixel of the columns in
view, the running maximum of its focus curve (``best``), the level of that maximum
(``argmax``), the image value there (the all-in-focus texture, ``tex``), for the
accumulating methods the curve's sums (``sums``, weights ``coef``) and optionally its
running minimum (``low``), and for the others the N-level ring (``fv``). Each frame
updates a region of these planes.

Done frame by frame, the update is memory bound: the state of a frame's region (about
1040 x 650 px, 9 to 29 bytes a pixel) is read and written once per frame, from memory.
:func:`apply_writes` takes the writes of several frames (those that arrived since the last
block reduction, :class:`Write`) and applies them strip of rows by strip of rows, every
frame's part of a strip in turn, so that the strip's state stays in cache across the
frames. Each pixel still sees the same operations in the same order (the frames in the
order they arrived, each with the OpenCV calls of one frame), so the state, and every
block reduced from it, is bit-identical to the frame-by-frame update (tested in
``tests/stages/test_focus_volume.py``; measured with ``bench/bench_accumulate.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np

__all__ = ["AccumulatorState", "Write", "apply_writes"]


class Write(NamedTuple):
    """One frame's values for rows [r0, r1) and ring slots ``cs`` of the state."""

    level: int
    focus: np.ndarray  # float32 (r1 - r0, columns), unit column stride
    image01: np.ndarray  # the frame's scaled image, same shape
    r0: int
    r1: int
    cs: slice


class AccumulatorState(NamedTuple):
    """The per-pixel planes a write updates (views into the focus volume's buffers)."""

    best: np.ndarray  # float32 (rows, ring): running maximum
    argmax: np.ndarray  # uint8/uint16 (rows, ring): its level
    tex: np.ndarray  # float32 (rows, ring): the image value at the maximum
    sums: np.ndarray  # float32 (S, rows, ring): sums of coef[:, level] * y (S may be 0)
    coef: np.ndarray  # float (S or more, N): the sums' weights
    low: np.ndarray | None  # float32 (rows, ring): running minimum, or None
    fv: np.ndarray | None  # float32 (N, rows, ring): every level, or None
    level_buf: np.ndarray  # (rows, >= columns of a write), argmax's dtype: scratch, by row
    #: float32 (N, ceil(rows / grid_step), ring): every level of every grid_step-th row
    #: (the curves a block's bias is judged on, kept where no N-level ring is), or None
    grid: np.ndarray | None = None
    grid_step: int = 16


def _update(state: AccumulatorState, w: Write, a: int, b: int) -> None:
    """Rows [a, b) of the state (within [w.r0, w.r1)) take write ``w``'s values."""
    rows = slice(a, b)
    cs = w.cs
    f = w.focus[a - w.r0:b - w.r0]
    level = w.level
    if state.fv is not None:
        state.fv[level, rows, cs] = f
    if state.grid is not None:
        k = state.grid_step
        g0, g1 = -(-a // k), -(-b // k)  # the grid rows g * k within [a, b)
        if g1 > g0:
            state.grid[level, g0:g1, cs] = f[g0 * k - a::k]
    for plane, c in zip(state.sums, state.coef[:len(state.sums), level], strict=True):
        c = float(c)
        view = plane[rows, cs]
        if c == 1.0:
            cv2.add(view, f, dst=view)
        elif c != 0.0:
            cv2.scaleAdd(f, c, view, dst=view)
    best = state.best[rows, cs]
    amax = state.argmax[rows, cs]
    sharper = cv2.compare(f, best, cv2.CMP_GT)
    tie = cv2.compare(f, best, cv2.CMP_EQ)
    if cv2.countNonZero(tie):
        lower = np.where(amax > level, 255, 0).astype(np.uint8)  # rare: ties only
        cv2.bitwise_or(sharper, cv2.bitwise_and(tie, lower), dst=sharper)
    cv2.max(f, best, dst=best)
    if state.low is not None:
        low = state.low[rows, cs]
        cv2.min(f, low, dst=low)
    lv = state.level_buf[a:b, :f.shape[1]]  # rows of its own: bands never share them
    lv.fill(level)
    cv2.copyTo(lv, sharper, amax)
    cv2.copyTo(w.image01[a - w.r0:b - w.r0], sharper, state.tex[rows, cs])


def apply_writes(state: AccumulatorState, writes: Sequence[Write], *,
                 cache_bytes: int, rows: tuple[int, int] | None = None) -> None:
    """Apply ``writes`` in order, strip of rows by strip of rows.

    Parameters
    ----------
    state : AccumulatorState
        The planes to update, in place.
    writes : sequence of Write
        The frames' writes, in the order they arrived.
    cache_bytes : int
        Bytes of state (over the columns the writes span) held in cache per strip.
    rows : (int, int), optional
        Only the state's rows [r0, r1) (a band worker's,
        :class:`sffscan.stages.bands.BandWorkers`); bands of the same writes may be
        applied at the same time, in any order.

    Notes
    -----
    Ties keep the lowest level, as :func:`~sffscan.stages.depth_levels.first_argmax`
    does: a later frame of a lower level (the staircase wrapped while the column was in
    view) wins a tie. A pixel's operations and their order do not depend on the strips.
    """
    if not writes:
        return
    lo = min(w.r0 for w in writes)
    hi = max(w.r1 for w in writes)
    if rows is not None:
        lo, hi = max(lo, rows[0]), min(hi, rows[1])
    span = max(w.cs.stop for w in writes) - min(w.cs.start for w in writes)
    per_px = (state.best.itemsize + state.argmax.itemsize + state.tex.itemsize
              + 4 * len(state.sums) + (4 if state.low is not None else 0))
    if len(writes) == 1:
        # One frame: nothing stays in cache across frames, so the strip only needs to hold
        # the frame's focus values (``cache_bytes`` of them) for its ~10 passes, as the
        # frame-by-frame update did before deferral. Strips sized for the whole state
        # (~29 B/px) were ~60 per frame, each ~10 OpenCV calls holding the GIL between
        # them: in the thread placement the accumulation's GIL time doubled (py-spy --gil,
        # default scan, 2 cores) and the scan lost 8 % of its frames/s.
        strip = max(16, cache_bytes // (4 * max(1, span)))
    else:
        strip = max(8, cache_bytes // (per_px * max(1, span)))
    for a in range(lo, hi, strip):
        b = min(a + strip, hi)
        for w in writes:
            s0, s1 = max(a, w.r0), min(b, w.r1)
            if s1 > s0:
                _update(state, w, s0, s1)
