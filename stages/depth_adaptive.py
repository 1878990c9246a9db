"""The adaptive depth estimator and its one-pass block reduction (SFF_NOTES.md section 3);
the simple peak estimators it builds on (the 3-point fits, the windowed centroid) and the
gathering of the levels about a peak are its sibling :mod:`sffscan.stages.depth_peak`'s.

* ``adaptive`` (:func:`adaptive_peak`): the curve's maximum (a 3-point Gaussian) where the
  focus window sees one height, else the windowed centroid; the default,
  ``adaptive_centroid``, takes the centroid of the 5 levels about the filtered peak instead
  of the 3-point Gaussian (``peak="centroid"``) where the stack's or block's curves do not
  pull a centroid from their maxima
  (:func:`sffscan.stages.depth_statistics.centroid_pull`).

The streaming depth stage (:mod:`sffscan.stages.focus_volume`) keeps the N focus levels of
the columns in view in a ring of ``(N, rows, ring)`` float32 planes and reduces a block of
columns once it is complete. For ``"adaptive"`` the reduction needs, per pixel, the 5 or 11
levels about its filtered peak and the curve's first harmonic over all N levels
(:func:`sffscan.stages.depth_harmonics.focus_confidence`). Done separately, those are two
passes over a block that does not fit in cache (N = 50, 1040 rows, 64 columns: 13 MB), and
the first one gathers values scattered over N planes of 5 MB each. :func:`adaptive_block`
does both in one pass: the block is copied in strips of rows that stay in cache
(:func:`sffscan.stages.depth_harmonics.volume_strips`, the copy the confidence's matrix
product needs anyway), and the levels about each pixel's peak are gathered from that copy.
Measured with ``bench/bench_depth_default.py`` (the depth stage's CPU per frame of a demo
scan). The confidence equals :func:`~sffscan.stages.depth_harmonics.focus_confidence`'s
(the same float32 matrix product over the same strips). The public names are also those of
:mod:`sffscan.stages.depth`.
"""

from __future__ import annotations

import numpy as np
from sffscan.stages.depth_harmonics import (
    STRIP_PIXELS,
    blas_view,
    confidence_from_sums,
    harmonic_table,
    strip_sums,
)
from sffscan.stages.depth_peak import (
    WCENTROID_HALF_WINDOW,
    _beyond,
    _flat_view,
    _nested_centroid_offsets,
    _parabola_offset,
    _pixel_offsets,
)

__all__ = [
    "ADAPTIVE_HALF_WINDOW",
    "ADAPTIVE_MAX_SPREAD",
    "PEAK_ESTIMATORS",
    "adaptive_block",
    "adaptive_peak",
]

ADAPTIVE_HALF_WINDOW = 5
"""Half width h of the ``"adaptive"`` method's centroid: 2h + 1 = 11 levels."""

ADAPTIVE_MAX_SPREAD = 2
"""Largest spread of filtered peaks (levels) in the focus window for which ``"adaptive"``
takes the curve's maximum (Gaussian 3-point fit) instead of its windowed centroid."""

PEAK_ESTIMATORS = ("gauss3", "centroid")
"""What :func:`adaptive_block` takes where the focus window sees one height: the curve's
maximum (3-point Gaussian) or the baseline-free centroid of the 5 levels about the filtered
peak."""


# ----------------------------------------------------------------------------- internals


def _gaussian_top(vals: list[np.ndarray], c: np.ndarray, n: int) -> np.ndarray:
    """The 3-point Gaussian at the largest of the levels ``c - 1 .. c + 1`` (the first of
    ties), from the levels ``c - 2 .. c + 2`` (beyond the range: -1, never the largest and
    never positive). Offset within ±0.5; none at the ends of the range, on a flat top or
    on values <= 0. Float32 levels. (Few temporaries: each value takes the same float32
    operations as written plainly.)"""
    ymm, ym, y0, yp, ypp = vals
    below = ym >= y0  # the largest is c - 1
    below &= ym >= yp
    above = yp > y0  # ... c + 1
    above &= ~below
    a, b, d = np.where(above, y0, ym), np.where(above, yp, y0), np.where(above, ypp, yp)
    np.copyto(a, ymm, where=below)
    np.copyto(b, ym, where=below)
    np.copyto(d, y0, where=below)
    top = c - below
    top += above
    ok = a > 0
    ok &= b > 0
    ok &= d > 0
    ok &= top > 0
    ok &= top < n - 1
    bad = ~ok
    for v in (a, b, d):  # the logarithms of the values used (1 where not ok)
        np.copyto(v, np.float32(1.0), where=bad)
        np.log(v, out=v)
    return (top + _parabola_offset(a, b, d, ok)).astype(np.float32)


def _gather(flat: np.ndarray, at: np.ndarray, st0: int, half_window: int,
            out: np.ndarray) -> None:
    """Levels ``c - h .. c + h`` of pixels whose level ``c`` lies at ``flat[at]`` (levels
    ``st0`` elements apart): ``out[j]`` gets level ``c + j - h``. Where that level is
    beyond 0..N-1 the value is some other of ``flat``'s (the index clipped), which
    :func:`_outside` then overwrites."""
    offsets = np.arange(-half_window * st0, (half_window + 1) * st0, st0, dtype=np.intp)
    np.take(flat, at[None, :] + offsets[:, None], out=out, mode="clip")


def _outside(c: np.ndarray, half_window: int, n: int, vals: np.ndarray, fill: float
             ) -> list[np.ndarray | None]:
    """The masks of :func:`~sffscan.stages.depth_peak._beyond`; the values of ``vals`` they
    mark are set to ``fill``."""
    masks = _beyond(c, half_window, n)
    for row, out in zip(vals, masks, strict=True):
        if out is not None:
            row[out] = fill
    return masks


# ----------------------------------------------------------------------------- estimators


def adaptive_block(vol: np.ndarray, centre: np.ndarray, spread: np.ndarray, *,
                   half_window: int = ADAPTIVE_HALF_WINDOW,
                   max_spread: int = ADAPTIVE_MAX_SPREAD, peak: str = "gauss3",
                   sums_out: np.ndarray | None = None, min_out: np.ndarray | None = None,
                   wide_peak_out: np.ndarray | None = None,
                   window_out: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (``"adaptive"``) and confidence of a block of the focus volume, in one pass.

    The depth is :func:`adaptive_peak`'s (documented there), the confidence
    :func:`~sffscan.stages.depth_harmonics.focus_confidence`'s, bit for bit; see the module
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
        (:func:`sffscan.stages.depth_levels.level_spread`).
    half_window : int, keyword-only
        Centroid half width h >= 2.
    max_spread : int, keyword-only
        Largest spread for which the curve's maximum is taken.
    peak : {"gauss3", "centroid"}, keyword-only
        The estimator where the spread is at most ``max_spread``: the 3-point Gaussian at
        the largest of the levels next to ``centre`` (``adaptive``), or the baseline-free
        centroid of the 5 levels ``centre - 2 .. centre + 2`` (``adaptive_centroid`` on
        even curves: two more levels than the 3-point fit, so less noise; but pulled into
        the tail of a lopsided curve, and on a clean Gaussian of sigma 2-3 levels up to
        0.08 levels away from ``centre`` by the window's minimum, where the 3-point Gaussian
        is exact: tests/stages/test_depth.py).
    sums_out : (3, H, W) ndarray of float32, optional, keyword-only
        Receives H_0, Re H_1 and Im H_1 of every curve (the confidence's sums; the curve's
        width, :func:`sffscan.stages.curve_shape.width_from_sums`, needs them).
    min_out : (H, W) ndarray of float32, optional, keyword-only
        Receives every curve's smallest value (from the same strips, while in cache).
    wide_peak_out : (H, W) ndarray of float32, optional, keyword-only
        Receives, where the spread exceeds ``max_spread``, what ``peak`` gives there (the
        depth with every pixel taken as a peak pixel, bit for bit: from the 5 middle levels
        of the wide window), NaN elsewhere
        (:func:`sffscan.stages.depth_choice.wide_choice`).
    window_out : (H, W) ndarray of float32, optional, keyword-only
        Receives :func:`~sffscan.stages.depth_peak.windowed_centroid`'s depth about
        ``centre`` (the 9 levels of
        :data:`~sffscan.stages.depth_peak.WCENTROID_HALF_WINDOW`) at every pixel, bit for
        bit, from the levels this pass gathers anyway (``half_window`` >= 4); for
        :func:`sffscan.stages.depth_window.window_choice`.

    Returns
    -------
    depth : (H, W) ndarray of float32
        Depth in fractional levels.
    confidence : (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1].
    """
    if half_window < 2:
        raise ValueError(f"half_window must be >= 2, got {half_window}")
    if peak not in PEAK_ESTIMATORS:
        raise ValueError(f"peak must be one of {PEAK_ESTIMATORS}, got {peak!r}")
    if window_out is not None and half_window < WCENTROID_HALF_WINDOW:
        raise ValueError(f"window_out needs half_window >= {WCENTROID_HALF_WINDOW}, "
                         f"got {half_window}")
    peak_centroid = peak == "centroid"
    n, height, width = vol.shape
    c = np.asarray(centre).astype(np.intp, copy=False).reshape(-1)
    at_peak = np.asarray(spread).reshape(-1) <= max_spread
    n_peak = int(np.count_nonzero(at_peak))
    h = half_window
    # levels c - 2 .. c + 2 of the peak pixels (c - 4 .. c + 4 where the 9-level centroid
    # is wanted too: one gather, in cache, instead of a second pass over the block)
    hw = WCENTROID_HALF_WINDOW
    hp = 2 if window_out is None else hw
    top = np.empty((2 * hp + 1, n_peak), np.float32)
    wide = np.empty((2 * h + 1, c.size - n_peak), np.float32)  # c - h .. c + h, the others

    table = harmonic_table(n)[[0, 2, 3]].astype(np.float32)
    sums = np.empty((3, height, width), np.float32)
    vol = blas_view(vol)
    flat, st0, st1, st2 = _flat_view(vol)
    at = _pixel_offsets(vol.shape[1:], st1, st2)
    at += c * st0  # each pixel's level c
    low = None if min_out is None else min_out.reshape(height, width)
    rows = max(1, STRIP_PIXELS // max(1, width))
    done_peak = done_wide = 0
    for r0 in range(0, height, rows):
        # a strip of rows read in place (no copy), its sums as focus_sums takes them
        r1 = min(r0 + rows, height)
        block = vol[:, r0:r1]
        strip_sums(table, block, out=sums[:, r0:r1])
        if low is not None:
            np.min(block, axis=0, out=low[r0:r1])
        p0, p1 = r0 * width, r1 * width  # the levels about each peak, while in cache
        sel = at_peak[p0:p1]
        local = np.flatnonzero(sel)
        if local.size:
            local += p0
            _gather(flat, at[local], st0, hp, top[:, done_peak:done_peak + local.size])
            done_peak += local.size
        if local.size < p1 - p0:
            others = np.flatnonzero(~sel)
            others += p0
            _gather(flat, at[others], st0, h, wide[:, done_wide:done_wide + others.size])
            done_wide += others.size

    depth = np.empty(c.shape, np.float32)
    win = None if window_out is None else np.empty(c.shape, np.float32)
    if n_peak:
        cp = c[at_peak]
        if not peak_centroid:  # the 3-point Gaussian's levels, -1 beyond the range
            five = top[hp - 2:hp + 3].copy() if win is not None else top[hp - 2:hp + 3]
            _outside(cp, 2, n, five, -1.0)
            depth[at_peak] = _gaussian_top(list(five), cp, n)
        # the 5-level and 9-level centroids in one pass (_nested_centroid_offsets)
        halves = (2,) * peak_centroid + (hw,) * (win is not None)
        if halves:
            masks = _outside(cp, hp, n, top, np.inf)
            offs = _nested_centroid_offsets(list(top[hp - halves[-1]:hp + halves[-1] + 1]),
                                            masks[hp - halves[-1]:hp + halves[-1] + 1], halves)
            if peak_centroid:
                depth[at_peak] = (cp + offs[0]).astype(np.float32)
            if win is not None:
                win[at_peak] = (cp + offs[-1]).astype(np.float32)
    alt = None if wide_peak_out is None else np.full(c.shape, np.nan, np.float32)
    if n_peak < c.size:
        cw = c[~at_peak]
        if alt is not None and not peak_centroid:  # before the fill below
            mid = wide[h - 2:h + 3].copy()
            _outside(cw, 2, n, mid, -1.0)
            alt[~at_peak] = _gaussian_top(list(mid), cw, n)
        # the 11-level centroid, and the 9-level and 5-level ones where wanted, in one pass
        wanted = {h} | ({hw} if win is not None else set()) | (
            {2} if alt is not None and peak_centroid else set())
        masks = _outside(cw, h, n, wide, np.inf)
        by_half = dict(zip(sorted(wanted), _nested_centroid_offsets(list(wide), masks,
                                                                    tuple(sorted(wanted))),
                           strict=True))
        if alt is not None and peak_centroid:
            alt[~at_peak] = (cw + by_half[2]).astype(np.float32)
        if win is not None:
            win[~at_peak] = (cw + by_half[hw]).astype(np.float32)
        depth[~at_peak] = (cw + by_half[h]).astype(np.float32)
    if wide_peak_out is not None and alt is not None:
        wide_peak_out[...] = alt.reshape(height, width)
    if window_out is not None and win is not None:
        window_out[...] = win.reshape(height, width)
    h0, re, im = sums
    if sums_out is not None:
        sums_out[...] = sums
    return depth.reshape(height, width), confidence_from_sums(h0, re, im)


def adaptive_peak(vol: np.ndarray, centre: np.ndarray, spread: np.ndarray, *,
                  half_window: int = ADAPTIVE_HALF_WINDOW,
                  max_spread: int = ADAPTIVE_MAX_SPREAD, peak: str = "gauss3") -> np.ndarray:
    """The curve's maximum where the focus window sees one height, else its windowed centroid.

    ``spread`` is the number of levels that the median-filtered peaks ``centre`` span over
    the focus measure's window about each pixel
    (:func:`~sffscan.stages.depth_levels.level_spread`): how many heights
    the window mixes into the pixel's focus curve.

    * ``spread > max_spread`` (a slope or an edge: the curve is a blend of peaks at the
      heights the window covers): the baseline-free centroid of the 2h + 1 levels about
      ``centre`` (:func:`~sffscan.stages.depth_peak.windowed_centroid`), which takes the
      middle of that blend.
    * ``spread <= max_spread`` (one height): the curve's own maximum: the largest of the
      levels ``centre - 1 .. centre + 1``, refined by the Gaussian (log-parabola) through it
      and its two neighbours (offset within ±0.5; none at the ends of the range, on a
      flat top or on values <= 0). A maximum does not move when the focus axis is
      stretched unevenly, where a centroid does: on lopsided curves (a thin lens' blur is
      even in 1/z, not in z) the centroid is pulled towards the longer tail.

    Parameters
    ----------
    vol : (N, H, W) ndarray of float
        Focus volume, finite (not checked); read in strips of rows
        (:func:`adaptive_block`).
    centre : (H, W) ndarray of int
        Median-filtered argmax, levels 0..N-1.
    spread : (H, W) ndarray of int
        Levels spanned by ``centre`` over the focus window
        (:func:`~sffscan.stages.depth_levels.level_spread`).
    half_window : int, keyword-only
        Centroid half width h >= 2. Default :data:`ADAPTIVE_HALF_WINDOW`.
    max_spread : int, keyword-only
        Default :data:`ADAPTIVE_MAX_SPREAD`.
    peak : {"gauss3", "centroid"}, keyword-only
        Where the spread is at most ``max_spread``: the curve's maximum as above
        (``"gauss3"``, the default) or the centroid of the 5 levels about ``centre``
        (:func:`adaptive_block`).

    Returns
    -------
    (H, W) ndarray of float32
        Depth in fractional levels.
    """
    # one implementation: the streaming reduction's, whose confidence is left unused here
    return adaptive_block(vol, centre, spread, half_window=half_window,
                          max_spread=max_spread, peak=peak)[0]
