"""The simple depth estimators that read the levels about each curve's peak (SFF_NOTES.md
section 3).

* the 3-point fits of ``gauss3`` and ``quadratic3`` (:func:`three_point_offset`): a
  parabola through the argmax and its two neighbours, on log values for the Gaussian;
* the windowed centroid of ``wcentroid`` (:func:`windowed_centroid`): the baseline-free
  centroid of the 2h + 1 levels about the median-filtered argmax.

Its sibling :mod:`sffscan.stages.depth_adaptive` holds ``adaptive`` and the default's
one-pass block reduction, which gather the levels about each peak with this module's
internals. The public names are also those of :mod:`sffscan.stages.depth`.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "WCENTROID_HALF_WINDOW",
    "three_point_offset",
    "windowed_centroid",
]

WCENTROID_HALF_WINDOW = 4
"""Half width h of the ``"wcentroid"`` window: 2h + 1 = 9 levels around the filtered peak."""


# ----------------------------------------------------------------------------- internals


def _flat_view(vol: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """One 1-D float32 view over ``vol``'s memory, first to last element (all inside its
    buffer), and its element strides; a float32 view with positive strides (a block of a
    ring buffer) is read in place, anything else is copied first."""
    n, rows, cols = vol.shape
    if vol.dtype != np.float32 or any(st <= 0 or st % 4 for st in vol.strides):
        vol = np.ascontiguousarray(vol, dtype=np.float32)
    st0, st1, st2 = (st // 4 for st in vol.strides)
    span = (n - 1) * st0 + (rows - 1) * st1 + (cols - 1) * st2 + 1
    return np.lib.stride_tricks.as_strided(vol, shape=(span,), strides=(4,)), st0, st1, st2


def _pixel_offsets(shape: tuple[int, ...], st1: int, st2: int) -> np.ndarray:
    """Element offset of every pixel's level 0, flat ``(H * W,)`` intp."""
    rows = np.arange(shape[0], dtype=np.intp)[:, None] * st1
    return (rows + np.arange(shape[1], dtype=np.intp)[None, :] * st2).reshape(-1)


def _beyond(c: np.ndarray, half_window: int, n: int) -> list[np.ndarray | None]:
    """For each window offset j = -h .. h, the mask of the pixels (``c`` within 0..N-1) whose
    level ``c + j`` is beyond the range 0..N-1, or None where no pixel's is: one comparison
    an offset (``c < -j`` or ``c > N - 1 - j``; the sum and two comparisons before
    2026-12-06 took twice the time, 0.10 ms a frame of the default's depth stage on the
    demo's plate, whose base lies a few levels above the range's start)."""
    lowest, highest = (int(c.min()), int(c.max())) if c.size else (0, 0)
    masks: list[np.ndarray | None] = []
    for j in range(-half_window, half_window + 1):
        # c lies in 0..N-1: c + j < 0 only for j < 0, c + j > N - 1 only for j > 0
        if j < 0 and lowest + j < 0:
            masks.append(c < -j)
        elif j > 0 and highest + j > n - 1:
            masks.append(c > n - 1 - j)
        else:
            masks.append(None)
    return masks


def _levels_at(flat: np.ndarray, at: np.ndarray, c: np.ndarray, st0: int, n: int,
               half_window: int, fill: float
               ) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """Levels ``c - h .. c + h`` of the pixels at offsets ``at``: 2h + 1 flat float32 arrays
    (levels beyond the range set to ``fill``), and for each a mask of those beyond the range
    (None where none is: :func:`_beyond`)."""
    vals: list[np.ndarray] = []
    outside = _beyond(c, half_window, n)
    first = at + c * st0
    for j, out in zip(range(-half_window, half_window + 1), outside, strict=True):
        if out is not None:
            v = flat.take(np.clip(c + j, 0, n - 1) * st0 + at)
            v[out] = fill
        else:  # every pixel's level exists: no clipping
            v = flat.take(first + j * st0)
        vals.append(v)
    return vals, outside


def _centroid_offset(vals: list[np.ndarray], outside: list[np.ndarray | None]) -> np.ndarray:
    """Centroid offset (levels, float32) of the window values above their minimum, 0 where
    nothing is above it (:func:`_nested_centroid_offsets` over the whole window); ``vals``
    holds +inf at the levels beyond the range and is not written."""
    return _nested_centroid_offsets(vals, outside, (len(vals) // 2,))[0]


def _nested_centroid_offsets(vals: list[np.ndarray], outside: list[np.ndarray | None],
                             halves: tuple[int, ...]) -> list[np.ndarray]:
    """For each half width h of ``halves`` (ascending, each within the window), the centroid
    offset (levels, float32) of the 2h + 1 middle values above their own minimum, 0 where
    nothing is above it: one pass from the middle level outwards.

    ``vals`` are the 2H + 1 levels about each pixel's centre (+inf at the levels beyond the
    range, whose ``outside`` masks give them no weight); not written. The sums are taken
    against the middle value (``v - v_0``, small where the curve has a pedestal) and the
    window's minimum comes off at the end (``s0 = sum(v - v_0) - K (min - v_0)``, K the levels
    within the range; the same for ``s1`` with the sum of their offsets), so that the 5-,
    9- and 11-level centroids of the default's block reduction take one pass over the
    11 levels instead of one each (2026-12-06: the window's weights were taken one window at
    a time before; the same values up to float32 rounding, and a window's centroid is the
    same bit for bit whichever longer window it was taken with)."""
    big = len(vals) // 2
    ref = vals[big]  # the middle level: never beyond the range
    floor = ref.copy()
    s0 = np.zeros(ref.shape, np.float32)
    s1 = np.zeros(ref.shape, np.float32)
    levels = 1  # the window's levels (their offsets sum to 0) ...
    missed: np.ndarray | None = None  # ... less those beyond the range, per pixel
    missed_sum: np.ndarray | None = None  # (and the sum of their offsets)
    wanted = set(halves)
    result: list[np.ndarray] = []
    for h in range(1, max(halves) + 1):
        for j in (-h, h):
            v, out = vals[big + j], outside[big + j]
            np.minimum(floor, v, out=floor)
            d = np.subtract(v, ref)
            if out is not None:
                d[out] = 0.0
                o = out.astype(np.float32)
                missed = o if missed is None else missed + o
                jo = o * np.float32(j)
                missed_sum = jo if missed_sum is None else missed_sum + jo
            levels += 1
            s0 += d
            d *= np.float32(j)
            s1 += d
        if h in wanted:
            low = np.subtract(floor, ref)  # <= 0
            k = np.float32(levels) if missed is None else np.float32(levels) - missed
            w0 = s0 - k * low
            w1 = s1 if missed_sum is None else s1 + missed_sum * low
            good = w0 > 0
            result.append(np.where(good, w1 / np.where(good, w0, np.float32(1.0)),
                                   np.float32(0.0)).astype(np.float32, copy=False))
    return result


def _parabola_offset(ym: np.ndarray, y0: np.ndarray, yp: np.ndarray, ok: np.ndarray
                     ) -> np.ndarray:
    """Vertex offset in [-0.5, 0.5] of the parabola through (-1, ym), (0, y0), (1, yp);
    0 where not ``ok`` or the denominator is not negative (a flat top)."""
    den = ym - 2 * y0 + yp
    ok = ok & (den < 0)
    off = np.where(ok, np.float32(0.5) * (ym - yp) / np.where(ok, den, np.float32(-1.0)),
                   np.float32(0.0))
    return np.clip(off, -0.5, 0.5)


# ----------------------------------------------------------------------------- estimators


def three_point_offset(vol: np.ndarray, a: np.ndarray, *, log: bool) -> np.ndarray:
    """Sub-level offset in [-0.5, 0.5] of a 3-point parabola through (a-1, a, a+1).

    On ``log`` values this is the Gaussian fit. Where ``a`` is 0 or N-1, a value is <= 0 (log
    fit), or the denominator is not negative (flat top), the offset is 0 (argmax fallback).
    """
    n = vol.shape[0]
    pixels = a.size
    interior = (a > 0) & (a < n - 1)
    flat = vol.reshape(-1)
    at = np.clip(a, 1, n - 2) * pixels + np.arange(pixels).reshape(a.shape)  # flat index
    ym, y0, yp = flat[at - pixels], flat[at], flat[at + pixels]
    if log:
        positive = (ym > 0) & (y0 > 0) & (yp > 0)
        interior &= positive
        ym, y0, yp = (np.log(np.where(positive, v, 1.0)) for v in (ym, y0, yp))
    return _parabola_offset(ym, y0, yp, interior).astype(np.float32)


def windowed_centroid(vol: np.ndarray, centre: np.ndarray, *,
                      half_window: int = WCENTROID_HALF_WINDOW) -> np.ndarray:
    """Baseline-free centroid of each curve over the 2h + 1 levels around ``centre``.

    For every pixel the levels ``centre - h .. centre + h`` that exist (the window is cut at
    0 and N - 1) are read; their minimum is subtracted (the floor of the curve, which
    otherwise pulls the centroid towards the window's middle) and the centroid of what is
    left is returned, in levels. Where the window holds no signal above its minimum (a flat
    curve) the result is ``centre``.

    Parameters
    ----------
    vol : (N, H, W) ndarray of float
        Focus volume; a float32 view with positive strides (a block of a ring buffer) is
        read in place, anything else is copied first.
    centre : (H, W) ndarray of int
        Window centres, levels 0..N-1.
    half_window : int, keyword-only
        h >= 1. Default :data:`WCENTROID_HALF_WINDOW`.

    Returns
    -------
    (H, W) ndarray of float32
        Depth in fractional levels.
    """
    flat, st0, st1, st2 = _flat_view(vol)
    c = np.asarray(centre).astype(np.intp, copy=False).reshape(-1)
    at = _pixel_offsets(vol.shape[1:], st1, st2)
    vals, outside = _levels_at(flat, at, c, st0, vol.shape[0], half_window, np.inf)
    return (c + _centroid_offset(vals, outside)).astype(np.float32).reshape(vol.shape[1:])
