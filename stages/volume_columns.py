"""The column geometry of the streaming focus volume (:mod:`sffscan.stages.focus_volume`):
which of a frame's columns can still bring new (column, level) pairs (:func:`new_columns`),
a volume's halo, rows and ring of columns (:func:`volume_geometry`), and which of its
columns are final and how they are cut into blocks (:func:`final_end`,
:func:`block_ranges`). The blocks' reduction to depth is :mod:`sffscan.stages.volume_reduce`'s.
"""

from __future__ import annotations

import numpy as np
from sffscan.stages import block_depth as blocks

__all__ = ["block_ranges", "final_end", "new_columns", "volume_geometry"]


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
    """A volume's halo of columns, its rows and its ring's columns (see
    :class:`~sffscan.stages.focus_volume.FocusVolume`)."""
    # the median's reach (+1), and for "adaptive" the spread window's beyond it, so that a
    # block's filtered peaks and spreads equal those of the whole volume
    peak = method in ("adaptive", *blocks.BLOCK_CHOICES)
    halo = median_size // 2 + 1 + (spread_size // 2 if peak else 0)
    h, w = frame_shape
    return halo, h + 2 * row_slack, w + 2 * halo + 2 * block_columns + 2 * col_slack


def final_end(count: np.ndarray, u0: int, u1: int, *, ring: int, n_levels: int,
              dead_below: int) -> int:
    """The end of the run of final columns from ``u0``: the first of internal columns
    [u0, u1) that is neither complete (seen at all ``n_levels``: ``count`` of its slot in a
    ring of ``ring``) nor dead (below ``dead_below``: it can no longer be completed), else
    ``u1``."""
    us = np.arange(u0, u1)
    final = (count[us % ring] == n_levels) | (us < dead_below)
    open_ = np.flatnonzero(~final)
    return u0 + (int(open_[0]) if open_.size else us.size)


def block_ranges(u0: int, stop: int, block: int, *, partial: bool) -> list[tuple[int, int]]:
    """Columns [u0, stop) as (first, end) blocks of ``block`` columns, in order: all of them,
    the last one shorter, where ``partial``; else only whole blocks (the rest waits)."""
    out = []
    while stop - u0 >= block or (partial and stop > u0):
        u1 = min(u0 + block, stop)
        out.append((u0, u1))
        u0 = u1
    return out
