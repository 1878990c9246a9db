"""The default depth method (``"adaptive"``): a block's depth and confidence in one pass.

The streaming depth stage (:mod:`sffscan.stages.focus_volume`) keeps the N focus levels of
the columns in view in a ring of ``(N, rows, ring)`` float32 planes and reduces a block of
columns once it is complete. For ``"adaptive"`` the reduction needs, per pixel, the 5 or 11
levels about its filtered peak (see :func:`sffscan.stages.depth.adaptive_peak`, which is
this module's depth alone) and the curve's first harmonic over all N levels
(:func:`sffscan.stages.depth.focus_confidence`).

Done separately, those are two passes over a block that does not fit in cache (N = 50,
1040 rows, 64 columns: 13 MB), and the first one gathers values scattered over N planes
of 5 MB each. :func:`adaptive_block` does both in one pass: the block is copied in strips
of rows that stay in cache (:func:`sffscan.stages.depth.volume_strips`, the copy the
confidence's matrix product needs anyway), and the levels about each pixel's peak are
gathered from that copy. Measured with ``bench/bench_depth_default.py`` (the depth stage's
CPU per frame of a demo scan); the figures are in the README. The confidence equals
:func:`focus_confidence`'s (the same float32 matrix product over the same strips).
"""

from __future__ import annotations

import numpy as np
from sffscan.stages.depth import (
    ADAPTIVE_HALF_WINDOW,
    ADAPTIVE_MAX_SPREAD,
    _beyond,
    _centroid_offset,
    _confidence,
    _gaussian_top,
    harmonic_table,
    volume_strips,
)

__all__ = ["adaptive_block"]


def _gather(strip: np.ndarray, local: np.ndarray, k: np.ndarray, half_window: int,
            n: int, out: np.ndarray) -> None:
    """Levels ``k - h .. k + h`` (clipped to the range) of the strip's pixels ``local``:
    ``out[j]`` gets level ``k + j - h``; ``strip`` is ``(N, P)`` C-ordered."""
    offsets = np.arange(-half_window, half_window + 1, dtype=np.intp)[:, None]
    idx = np.clip(k[None, :] + offsets, 0, n - 1)
    idx *= strip.shape[1]
    idx += local[None, :]
    np.take(strip.reshape(-1), idx, out=out)


def _outside(c: np.ndarray, half_window: int, n: int, vals: np.ndarray, fill: float
             ) -> list[np.ndarray | None]:
    """The masks of :func:`sffscan.stages.depth._beyond`; the values of ``vals`` they mark
    are set to ``fill``."""
    masks = _beyond(c, half_window, n)
    for row, out in zip(vals, masks, strict=True):
        if out is not None:
            row[out] = fill
    return masks


def adaptive_block(vol: np.ndarray, centre: np.ndarray, spread: np.ndarray, *,
                   half_window: int = ADAPTIVE_HALF_WINDOW,
                   max_spread: int = ADAPTIVE_MAX_SPREAD,
                   sums_out: np.ndarray | None = None, min_out: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (``"adaptive"``) and confidence of a block of the focus volume, in one pass.

    The depth is :func:`sffscan.stages.depth.adaptive_peak`'s (documented there), the
    confidence :func:`sffscan.stages.depth.focus_confidence`'s, bit for bit; see the module
    for why it is one pass.

    Parameters
    ----------
    vol : (N, H, W) ndarray of float32
        Focus volume, finite (not checked); a strided view (a block of a ring) is read in
        place.
    centre : (H, W) ndarray of int
        Median-filtered argmax, levels 0..N-1.
    spread : (H, W) ndarray of int
        Levels spanned by ``centre`` over the focus window
        (:func:`sffscan.stages.depth.level_spread`).
    half_window : int, keyword-only
        Centroid half width h >= 2.
    max_spread : int, keyword-only
        Largest spread for which the curve's maximum is taken.
    sums_out : (3, H, W) ndarray of float32, optional, keyword-only
        Receives H_0, Re H_1 and Im H_1 of every curve (the confidence's sums; the curve's
        width, :func:`sffscan.stages.depth_uncertainty.width_from_sums`, needs them).
    min_out : (H, W) ndarray of float32, optional, keyword-only
        Receives every curve's smallest value (from the same strips, while in cache).

    Returns
    -------
    depth : (H, W) ndarray of float32
        Depth in fractional levels.
    confidence : (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1].
    """
    if half_window < 2:
        raise ValueError(f"half_window must be >= 2, got {half_window}")
    n, height, width = vol.shape
    c = np.asarray(centre).astype(np.intp, copy=False).reshape(-1)
    peak = np.asarray(spread).reshape(-1) <= max_spread
    n_peak = int(np.count_nonzero(peak))
    h = half_window
    top = np.empty((5, n_peak), np.float32)  # levels c - 2 .. c + 2 of the peak pixels
    wide = np.empty((2 * h + 1, c.size - n_peak), np.float32)  # c - h .. c + h, the others

    table = harmonic_table(n)[[0, 2, 3]].astype(np.float32)
    sums = np.empty((3, height * width), np.float32)
    done_peak = done_wide = 0
    low = None if min_out is None else min_out.reshape(-1)
    for p0, p1, strip in volume_strips(vol):
        np.matmul(table, strip, out=sums[:, p0:p1])
        if low is not None:
            np.min(strip, axis=0, out=low[p0:p1])
        sel = peak[p0:p1]
        local = np.flatnonzero(sel)
        k = c[p0:p1]
        if local.size:
            _gather(strip, local, k[local], 2, n, top[:, done_peak:done_peak + local.size])
            done_peak += local.size
        if local.size < p1 - p0:
            others = np.flatnonzero(~sel)
            _gather(strip, others, k[others], h, n, wide[:, done_wide:done_wide + others.size])
            done_wide += others.size

    depth = np.empty(c.shape, np.float32)
    if n_peak:
        cp = c[peak]
        _outside(cp, 2, n, top, -1.0)
        depth[peak] = _gaussian_top(list(top), cp, n)
    if n_peak < c.size:
        cw = c[~peak]
        masks = _outside(cw, h, n, wide, np.inf)
        depth[~peak] = (cw + _centroid_offset(list(wide), masks)).astype(np.float32)
    h0, re, im = sums.reshape(3, height, width)
    if sums_out is not None:
        sums_out[...] = sums.reshape(3, height, width)
    return depth.reshape(height, width), _confidence(h0, re, im)
