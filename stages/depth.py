"""Depth from a focus volume: peak localisation along the focus axis (SFF_NOTES.md section 3).

Conventions
-----------
A focus volume is an ``(N, H, W)`` float array of focus-measure values (>= 0); axis 0 is
the focus level ``k = 0 .. N-1``. A pixel's focus curve is ``y_k = volume[k, row, col]``.
Depth is returned in *fractional level units* (0 = level 0, 1 = level 1, ...) and mapped to
height with :func:`levels_to_height`.

Every method also returns the same confidence map

    confidence = |H_1| / H_0,   H_1 = sum_k y_k exp(-2 pi i k / N),   H_0 = sum_k y_k,

i.e. the relative strength of the first DFT harmonic: about 1 for a single narrow peak,
near 0 for a flat or noisy curve; set to 0 where ``H_0 <= 0`` and clipped to [0, 1].

All functions are pure and vectorised (no Python loops over pixels): the volume is used as
float32, and the harmonics come from one matrix product with a small (4, N) cos/sin table,
accumulated in float64.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import cv2
import numpy as np

__all__ = [
    "DEFAULT_METHOD",
    "DEPTH_METHODS",
    "STREAMING_METHODS",
    "ADAPTIVE_HALF_WINDOW",
    "ADAPTIVE_MAX_SPREAD",
    "WCENTROID_HALF_WINDOW",
    "adaptive_peak",
    "all_in_focus",
    "depth_from_focus",
    "depth_from_harmonics",
    "focus_confidence",
    "focus_sums",
    "harmonic_table",
    "level_spread",
    "levels_from_heights",
    "levels_to_height",
    "median_filter_levels",
    "spc_by_roll",
    "volume_strips",
    "windowed_centroid",
]

DEPTH_METHODS = ("argmax", "gauss3", "quadratic3", "centroid", "pc", "spc", "wcentroid",
                 "adaptive")
"""Names accepted by :func:`depth_from_focus` as ``method``."""

STREAMING_METHODS = ("argmax", "centroid", "pc", "spc")
"""Methods that need only the sums of :func:`harmonic_table` and the argmax of each curve
(:func:`depth_from_harmonics`), so a streaming accumulator needs no N-level volume."""

DEFAULT_METHOD = "adaptive"
"""The default depth method of scan, replay and stack (see :func:`adaptive_peak`)."""

WCENTROID_HALF_WINDOW = 4
"""Half width h of the ``"wcentroid"`` window: 2h + 1 = 9 levels around the filtered peak."""

ADAPTIVE_HALF_WINDOW = 5
"""Half width h of the ``"adaptive"`` method's centroid: 2h + 1 = 11 levels."""

ADAPTIVE_MAX_SPREAD = 2
"""Largest spread of filtered peaks (levels) in the focus window for which ``"adaptive"``
takes the curve's maximum (Gaussian 3-point fit) instead of its windowed centroid."""

STRIP_PIXELS = 4096
"""Pixels per strip of :func:`volume_strips`: N = 50 float32 levels of 4096 pixels are
800 KiB, which stay in cache."""


# ----------------------------------------------------------------------------- validation


def _check_volume(volume: np.ndarray) -> np.ndarray:
    """Return ``volume`` as (N, H, W) float32 after shape/dtype checks (finiteness separately)."""
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise ValueError(f"volume must be 3-D (N, H, W), got shape {vol.shape}")
    if vol.shape[0] < 3:
        raise ValueError(f"volume needs at least 3 focus levels (axis 0), got {vol.shape[0]}")
    if not (np.issubdtype(vol.dtype, np.floating) or np.issubdtype(vol.dtype, np.integer)):
        raise ValueError(f"volume must be a real numeric array, got dtype {vol.dtype}")
    return np.ascontiguousarray(vol, dtype=np.float32)


def _raise_not_finite(vol: np.ndarray) -> None:
    """Raise a ValueError naming the first level with NaN or inf (or an overflow)."""
    flat = vol.reshape(vol.shape[0], -1)
    for kind, test in (("NaN", np.isnan), ("inf", np.isinf)):
        levels = np.flatnonzero(test(flat).any(axis=1))
        if levels.size:
            raise ValueError(f"volume contains {kind} at level {int(levels[0])}")
    raise ValueError("volume contains values that are not finite")


def check_odd_size(value: int, *, name: str, minimum: int) -> int:
    """``value`` as an int if it is an odd integer >= ``minimum``; else ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an odd integer >= {minimum}, got {value!r}")
    if value < minimum or value % 2 == 0:
        raise ValueError(f"{name} must be an odd integer >= {minimum}, got {value}")
    return int(value)


def _check_median_size(median_size: int) -> int:
    return check_odd_size(median_size, name="median_size", minimum=1)


# ----------------------------------------------------------------------------- building blocks


def harmonic_table(n_levels: int) -> np.ndarray:
    """``(4, N)`` float64 weights of the curve sums: 1, k, cos(2 pi k / N), -sin(2 pi k / N).

    ``table @ y`` gives H_0 = sum y, sum k y, Re H_1 and Im H_1 of a focus curve ``y``; a
    streaming accumulator adds ``table[:, k] * y_k`` as level ``k`` arrives.
    """
    k = np.arange(n_levels, dtype=np.float64)
    theta = 2.0 * np.pi * k / n_levels
    return np.stack((np.ones(n_levels), k, np.cos(theta), -np.sin(theta)))


def _moments(vol: np.ndarray) -> np.ndarray:
    """``(4, H, W)`` float64: H_0 = sum y, sum k y, Re H_1, Im H_1 of every focus curve.

    One matrix product with the ``(4, N)`` :func:`harmonic_table`, accumulated in float64
    (float32 accumulation costs up to ~1e-3 levels of PC phase on curves whose first harmonic
    is weak). Done over blocks of rows so the float64 copy of the volume stays in cache; a
    strided view (a block of a ring buffer) is read in place.
    """
    n, height, width = vol.shape
    table = harmonic_table(n)
    out = np.empty((4, height * width), dtype=np.float64)
    rows = max(1, max(256, (1 << 17) // n) // max(1, width))  # ~1 MiB of float64 (L2)
    buf = np.empty((n, min(rows, height) * width), dtype=np.float64)
    for i in range(0, height, rows):
        r = min(rows, height - i)
        np.copyto(buf[:, :r * width].reshape(n, r, width), vol[:, i:i + r])
        np.matmul(table, buf[:, :r * width], out=out[:, i * width:(i + r) * width])
    return out.reshape((4, height, width))


def _confidence(h0: np.ndarray, re: np.ndarray, im: np.ndarray) -> np.ndarray:
    """``|H_1| / H_0`` clipped to [0, 1], 0 where ``H_0 <= 0``; float32."""
    positive = h0 > 0
    confidence = np.sqrt(re * re + im * im) / np.where(positive, h0, 1.0)
    return np.clip(np.where(positive, confidence, 0.0), 0.0, 1.0).astype(np.float32)


def focus_confidence(volume: np.ndarray) -> np.ndarray:
    """The confidence every method of :func:`depth_from_focus` returns, alone.

    The three sums come from a float32 matrix product (numpy's BLAS; 3x faster than
    ``cv2.gemm`` on these shapes, measured) over chunks of ~4096 pixels copied out of the
    (strided) volume: faster than :func:`_moments`' float64 product, and within 1e-7 of it
    for N = 50 (a confidence needs no more; the phase methods do).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float32
        Focus volume (finite; not checked), e.g. a strided view of a ring buffer.

    Returns
    -------
    (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1] (0 where ``H_0 <= 0``).
    """
    h0, re, im = focus_sums(volume)
    return _confidence(h0, re, im)


def focus_sums(volume: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` float32: H_0, Re H_1 and Im H_1 of every curve (the sums of
    :func:`focus_confidence`, from the same float32 product over strips)."""
    n, height, width = volume.shape
    table = harmonic_table(n)[[0, 2, 3]].astype(np.float32)
    sums = np.empty((3, height * width), np.float32)
    for p0, p1, strip in volume_strips(volume):
        np.matmul(table, strip, out=sums[:, p0:p1])
    return sums.reshape(3, height, width)


def volume_strips(volume: np.ndarray) -> Iterator[tuple[int, int, np.ndarray]]:
    """The volume in strips of whole rows, about :data:`STRIP_PIXELS` pixels each, each
    copied into one C-ordered ``(N, P)`` float32 buffer (reused: a strip is valid until the
    next is yielded): ``(first pixel, end pixel, strip)``, pixels counted row by row.

    A strided volume (a block of a ring buffer) is read once, in pieces that stay in cache
    for whatever the caller does with each strip.
    """
    n, height, width = volume.shape
    rows = max(1, STRIP_PIXELS // max(1, width))
    buf = np.empty((n, min(rows, height) * width), np.float32)
    for i in range(0, height, rows):
        r = min(rows, height - i)
        strip = buf[:, :r * width]
        np.copyto(strip.reshape(n, r, width), volume[:, i:i + r])
        yield i * width, (i + r) * width, strip


def _argmax(vol: np.ndarray) -> np.ndarray:
    """Index of the first maximum along axis 0, ``(H, W)`` intp (``vol`` free of NaN).

    Same result as ``np.argmax(vol, axis=0)``, about 5x faster on C-ordered (N, H, W) data:
    a contiguous max-reduction, then one equality pass per level, last level first.
    """
    peak = vol.max(axis=0)
    idx = np.zeros(peak.shape, dtype=np.intp)
    for k in range(vol.shape[0] - 1, 0, -1):
        np.copyto(idx, k, where=vol[k] == peak)
    np.copyto(idx, 0, where=vol[0] == peak)
    return idx


def median_filter_levels(levels: np.ndarray, size: int, n_levels: int) -> np.ndarray:
    """Median of integer level indices over size x size windows, replicated borders.

    ``cv2.medianBlur`` on uint8 when the levels fit (N <= 256; it takes any odd size there),
    otherwise an equivalent (slower) numpy sliding-window median.
    """
    if size == 1:
        return levels
    if n_levels <= 256:
        return cv2.medianBlur(levels.astype(np.uint8), size).astype(np.intp)
    r = size // 2
    padded = np.pad(levels.astype(np.int32), r, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size))
    out = np.empty(levels.shape, dtype=np.intp)
    rows = max(1, (1 << 22) // max(1, levels.shape[1] * size * size))  # bound the temporaries
    for i in range(0, levels.shape[0], rows):
        block = windows[i : i + rows].reshape(*windows[i : i + rows].shape[:2], -1)
        out[i : i + rows] = np.median(block, axis=-1).astype(np.intp)
    return out


def _spc_shift(vol: np.ndarray, median_size: int) -> np.ndarray:
    """Per-pixel circular shift ``s = round(N/2) - median(argmax)``, ``(H, W)`` intp.

    ``round`` is MATLAB's (halves away from zero): ``round(N/2) = (N + 1) // 2``.
    """
    return _spc_shift_of(_argmax(vol), median_size, vol.shape[0])


def _spc_shift_of(argmax: np.ndarray, median_size: int, n: int) -> np.ndarray:
    """:func:`_spc_shift` from the argmax map."""
    return (n + 1) // 2 - median_filter_levels(argmax, median_size, n)


def _wrap(x: np.ndarray, n: int) -> np.ndarray:
    """``x mod n`` in [0, n) (``np.mod`` can round a tiny negative ``x`` up to exactly ``n``)."""
    out = np.mod(x, float(n))
    out[out >= n] -= n
    return out


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
    """For each window offset j = -h .. h, the mask of the pixels whose level ``c + j`` is
    beyond the range 0..N-1, or None where no pixel's is."""
    lowest, highest = (int(c.min()), int(c.max())) if c.size else (0, 0)
    masks: list[np.ndarray | None] = []
    for j in range(-half_window, half_window + 1):
        if lowest + j < 0 or highest + j > n - 1:
            k = c + j
            masks.append((k < 0) | (k > n - 1))
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
    nothing is above it; ``vals`` (levels beyond the range: +inf) is overwritten."""
    half_window = len(vals) // 2
    floor = vals[0].copy()
    for v in vals[1:]:
        np.minimum(floor, v, out=floor)
    s0 = np.zeros(floor.shape, np.float32)
    s1 = np.zeros(floor.shape, np.float32)
    for j, v, out in zip(range(-half_window, half_window + 1), vals, outside, strict=True):
        wgt = np.subtract(v, floor, out=v)
        if out is not None:
            wgt[out] = 0.0
        s0 += wgt
        if j:
            s1 += np.float32(j) * wgt
    good = s0 > 0
    return np.where(good, s1 / np.where(good, s0, np.float32(1.0)), np.float32(0.0))


def _gaussian_top(vals: list[np.ndarray], c: np.ndarray, n: int) -> np.ndarray:
    """The 3-point Gaussian at the largest of the levels ``c - 1 .. c + 1`` (the first of
    ties), from the levels ``c - 2 .. c + 2`` (beyond the range: -1, never the largest and
    never positive). Offset within ±0.5; none at the ends of the range, on a flat top or
    on values <= 0. Float32 levels."""
    ymm, ym, y0, yp, ypp = vals
    below = (ym >= y0) & (ym >= yp)  # the largest is c - 1
    above = ~below & (yp > y0)  # ... c + 1
    a = np.where(below, ymm, np.where(above, y0, ym))
    b = np.where(below, ym, np.where(above, yp, y0))
    d = np.where(below, y0, np.where(above, ypp, yp))
    top = c - below + above
    ok = (a > 0) & (b > 0) & (d > 0) & (top > 0) & (top < n - 1)
    la, lb, ld = (np.log(np.where(ok, v, np.float32(1.0))) for v in (a, b, d))
    return (top + _parabola_offset(la, lb, ld, ok)).astype(np.float32)


def _parabola_offset(ym: np.ndarray, y0: np.ndarray, yp: np.ndarray, ok: np.ndarray
                     ) -> np.ndarray:
    """Vertex offset in [-0.5, 0.5] of the parabola through (-1, ym), (0, y0), (1, yp);
    0 where not ``ok`` or the denominator is not negative (a flat top)."""
    den = ym - 2 * y0 + yp
    ok = ok & (den < 0)
    off = np.where(ok, np.float32(0.5) * (ym - yp) / np.where(ok, den, np.float32(-1.0)),
                   np.float32(0.0))
    return np.clip(off, -0.5, 0.5)


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


def level_spread(centre: np.ndarray, size: int, n_levels: int) -> np.ndarray:
    """Spread of integer levels over size x size windows: local maximum - minimum.

    Replicated borders (``cv2.dilate`` / ``cv2.erode`` on uint8 when N <= 256, else
    :func:`scipy.ndimage.maximum_filter` / ``minimum_filter``).

    Parameters
    ----------
    centre : (H, W) ndarray of int
        Levels 0..N-1 (the median-filtered argmax).
    size : int
        Odd window size, px (the focus measure's window k).
    n_levels : int
        Number of levels N.

    Returns
    -------
    (H, W) ndarray of intp
        Levels spanned by each pixel's window.
    """
    size = check_odd_size(size, name="spread_size", minimum=1)
    if size == 1:
        return np.zeros(np.shape(centre), np.intp)
    if n_levels <= 256:
        a8 = np.asarray(centre).astype(np.uint8)
        kernel = np.ones((size, size), np.uint8)
        hi = cv2.dilate(a8, kernel, borderType=cv2.BORDER_REPLICATE)
        lo = cv2.erode(a8, kernel, borderType=cv2.BORDER_REPLICATE)
        return hi.astype(np.intp) - lo.astype(np.intp)
    from scipy import ndimage

    a = np.asarray(centre).astype(np.int64)
    return (ndimage.maximum_filter(a, size, mode="nearest")
            - ndimage.minimum_filter(a, size, mode="nearest")).astype(np.intp)


def adaptive_peak(vol: np.ndarray, centre: np.ndarray, spread: np.ndarray, *,
                  half_window: int = ADAPTIVE_HALF_WINDOW,
                  max_spread: int = ADAPTIVE_MAX_SPREAD) -> np.ndarray:
    """The curve's maximum where the focus window sees one height, else its windowed centroid.

    ``spread`` is the number of levels that the median-filtered peaks ``centre`` span over
    the focus measure's window about each pixel (:func:`level_spread`): how many heights
    the window mixes into the pixel's focus curve.

    * ``spread > max_spread`` (a slope or an edge: the curve is a blend of peaks at the
      heights the window covers): the baseline-free centroid of the 2h + 1 levels about
      ``centre`` (:func:`windowed_centroid`), which takes the middle of that blend.
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
        (:func:`sffscan.stages.depth_blocks.adaptive_block`).
    centre : (H, W) ndarray of int
        Median-filtered argmax, levels 0..N-1.
    spread : (H, W) ndarray of int
        Levels spanned by ``centre`` over the focus window (:func:`level_spread`).
    half_window : int, keyword-only
        Centroid half width h >= 2. Default :data:`ADAPTIVE_HALF_WINDOW`.
    max_spread : int, keyword-only
        Default :data:`ADAPTIVE_MAX_SPREAD`.

    Returns
    -------
    (H, W) ndarray of float32
        Depth in fractional levels.
    """
    # one implementation: the streaming reduction's, whose confidence is left unused here
    from sffscan.stages.depth_blocks import adaptive_block

    return adaptive_block(vol, centre, spread, half_window=half_window,
                          max_spread=max_spread)[0]


def _three_point(vol: np.ndarray, a: np.ndarray, *, log: bool) -> np.ndarray:
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


# ----------------------------------------------------------------------------- public API


def depth_from_focus(
    volume: np.ndarray, *, method: str = "spc", median_size: int = 11,
    argmax: np.ndarray | None = None, spread_size: int = 9,
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-level focus peak and its confidence for every pixel of a focus volume.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume (values >= 0), N >= 3 levels along axis 0; read as float32.
    method : str, keyword-only
        One of :data:`DEPTH_METHODS`:

        ``"argmax"``
            Index of the (first) largest value; integer-valued.
        ``"gauss3"``
            Gaussian through the argmax and its two neighbours (parabola on log values);
            exact for a sampled Gaussian.
        ``"quadratic3"``
            Parabola through the same three points.
            Both 3-point fits fall back to the argmax at the ends (argmax 0 or N-1), on a
            flat top (denominator >= 0) and, for ``gauss3``, on values <= 0.
        ``"centroid"``
            ``sum(k y_k) / sum(y_k)`` (argmax where the sum is <= 0).
        ``"pc"``
            Phase correlation: ``(-angle(H_1) N / (2 pi)) mod N``, in [0, N).
        ``"adaptive"`` (the default of scan, replay and stack)
            The argmax, median filtered as for SPC (``a_med``); where ``a_med`` spans at
            most :data:`ADAPTIVE_MAX_SPREAD` levels over the ``spread_size`` x
            ``spread_size`` focus window about the pixel, the curve's maximum next to
            ``a_med`` refined by a 3-point Gaussian; elsewhere the windowed centroid of
            the 2h + 1 = 11 levels about ``a_med`` (:func:`adaptive_peak`).
        ``"wcentroid"``
            Windowed centroid about the filtered peak: the argmax, median filtered over
            ``median_size`` x ``median_size`` pixels as for SPC (``a_med``), is the centre of
            a window of 2h + 1 = 9 levels (:data:`WCENTROID_HALF_WINDOW`, cut at the ends of
            the range); the window's minimum is subtracted and the centroid of the rest is
            the depth (:func:`windowed_centroid`). The median keeps a noisy or flat curve's
            stray maximum from moving the window (what spoils argmax, gauss3 and
            quadratic3 with noise); the window keeps the curve's far tails and noise floor
            out of the estimate (what spoils centroid and PC).
        ``"spc"``
            Shifted phase correlation: argmax, median filtered over ``median_size`` x
            ``median_size`` pixels (``a_med``); per-pixel shift ``s = round(N/2) - a_med``
            that would move ``a_med`` to the centre; PC of the shifted curve; minus ``s``.
            The curve is not rolled: ``np.roll(y, s)`` multiplies ``H_1`` by
            ``exp(-2 pi i s / N)``, i.e. adds ``-2 pi s / N`` to its angle, so the rotation is
            applied to the angle directly: ``depth = ((phi + s) mod N) - s`` with
            ``phi = -angle(H_1) N / (2 pi)``. No modulo after undoing the shift: the result
            lies in ``[a_med - round(N/2), a_med - round(N/2) + N)``, unwrapped around the
            filtered argmax. Same result as :func:`spc_by_roll`.
    median_size : int, keyword-only
        Odd median-filter size for ``"spc"``, ``"wcentroid"`` and ``"adaptive"`` (1 = no
        filtering).
        Default 11. The thesis used
        10 x 10; an even window has no centre pixel (the median would be shifted by half a
        pixel and an average of two levels), and ``cv2.medianBlur`` requires an odd size, so
        the nearest odd size above is the default. Validated for every method.
    argmax : (H, W) ndarray of int, optional, keyword-only
        Each curve's first maximum, if already known (a streaming accumulator keeps it as
        the levels arrive); computed from ``volume`` when not given.
    spread_size : int, keyword-only
        Odd window, px, over which ``"adaptive"`` measures the spread of the filtered
        peaks: the focus measure's window k. Default 9. Validated for every method.

    Returns
    -------
    depth : (H, W) ndarray of float32
        Peak position in fractional level units.
    confidence : (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1] (0 where ``H_0 <= 0``), the same for every method.

    Raises
    ------
    ValueError
        If ``volume`` is not 3-D, has fewer than 3 levels, contains NaN or inf (the message
        names the first such level), or ``method`` / ``median_size`` is invalid.
    """
    if method not in DEPTH_METHODS:
        raise ValueError(f"method must be one of {DEPTH_METHODS}, got {method!r}")
    median_size = _check_median_size(median_size)
    spread_size = check_odd_size(spread_size, name="spread_size", minimum=1)
    vol = _check_volume(volume)
    n = vol.shape[0]

    h0, hk, re, im = _moments(vol)
    if not np.isfinite(h0).all():  # NaN / inf anywhere in a curve makes its sum non-finite
        _raise_not_finite(vol)
    a: np.ndarray | None = None
    if argmax is not None and method != "pc":
        a = np.asarray(argmax)
        if a.shape != vol.shape[1:]:
            raise ValueError(f"argmax shape {a.shape} differs from the volume's {vol.shape[1:]}")
        a = a.astype(np.intp, copy=False)
    elif method != "pc":
        a = _argmax(vol)
    if method in STREAMING_METHODS:
        return _from_harmonics(h0, hk, re, im, a, n, method, median_size)
    assert a is not None
    depth, confidence = _from_harmonics(h0, hk, re, im, a, n, "argmax", median_size)
    if method in ("wcentroid", "adaptive"):
        centre = median_filter_levels(a, median_size, n)
        if method == "wcentroid":
            return windowed_centroid(vol, centre), confidence
        return adaptive_peak(vol, centre, level_spread(centre, spread_size, n)), confidence
    depth = a + _three_point(vol, a, log=method == "gauss3")
    return depth.astype(np.float32, copy=False), confidence


def _from_harmonics(h0: np.ndarray, hk: np.ndarray, re: np.ndarray, im: np.ndarray,
                    a: np.ndarray | None, n: int, method: str, median_size: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence from the curve sums and argmax (checked inputs)."""
    positive = h0 > 0
    confidence = _confidence(h0, re, im)

    if method in ("pc", "spc"):
        phi = np.arctan2(im, re) * (-n / (2.0 * math.pi))
        if method == "pc":
            depth = _wrap(phi, n)
        else:
            assert a is not None
            s = _spc_shift_of(a, median_size, n)
            depth = _wrap(phi + s, n) - s
    else:
        assert a is not None
        if method == "argmax":
            depth = a.astype(np.float32)
        else:  # centroid
            depth = np.where(positive, hk / np.where(positive, h0, 1.0), a)
    return depth.astype(np.float32, copy=False), confidence


def depth_from_harmonics(
    sums: np.ndarray, argmax: np.ndarray | None, *, n_levels: int, method: str = "spc",
    median_size: int = 11,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence from each curve's sums and argmax, without the curves.

    What :func:`depth_from_focus` computes for the methods in :data:`STREAMING_METHODS`,
    from the quantities a streaming accumulator can keep as the levels arrive one by one:
    ``sums = harmonic_table(N) @ y`` and the index of the curve's (first) maximum.

    Parameters
    ----------
    sums : (4, H, W) ndarray of float
        H_0 = sum y, sum k y, Re H_1, Im H_1 of every pixel's curve (see
        :func:`harmonic_table`). Computed in float32 when given float32 (sums accumulated
        in float32 hold no more than that), else in float64.
    argmax : (H, W) ndarray of int, or None
        Level of each curve's first maximum, 0..N-1; may be None for ``"pc"`` only.
    n_levels : int, keyword-only
        Number of focus levels N >= 3.
    method : {"argmax", "centroid", "pc", "spc"}, keyword-only
        As in :func:`depth_from_focus`.
    median_size : int, keyword-only
        Odd SPC median-filter size, as in :func:`depth_from_focus`.

    Returns
    -------
    depth, confidence : (H, W) ndarray of float32
        As :func:`depth_from_focus`: fractional levels, and ``|H_1| / H_0`` in [0, 1].

    Raises
    ------
    ValueError
        Unknown ``method`` (or one that needs the curve), bad ``median_size``, N < 3, shapes
        that do not match, non-finite sums, or a missing ``argmax``.
    """
    if method not in STREAMING_METHODS:
        raise ValueError(f"method must be one of {STREAMING_METHODS}, got {method!r}")
    median_size = _check_median_size(median_size)
    if n_levels < 3:
        raise ValueError(f"n_levels must be at least 3, got {n_levels}")
    sums = np.asarray(sums)
    if sums.dtype != np.float32:
        sums = sums.astype(np.float64)
    if sums.ndim != 3 or sums.shape[0] != 4:
        raise ValueError(f"sums must be (4, H, W), got shape {sums.shape}")
    if not np.isfinite(sums).all():
        raise ValueError("sums contain NaN or inf")
    a = None
    if argmax is not None:
        a = np.asarray(argmax)
        if a.shape != sums.shape[1:]:
            raise ValueError(f"argmax shape {a.shape} differs from the sums' {sums.shape[1:]}")
        a = a.astype(np.intp, copy=False)
    elif method != "pc":
        raise ValueError(f"method {method!r} needs the argmax of every curve")
    h0, hk, re, im = sums
    return _from_harmonics(h0, hk, re, im, a, n_levels, method, median_size)


def spc_by_roll(volume: np.ndarray, *, median_size: int = 11) -> np.ndarray:
    """SPC by its literal definition, for tests: roll every curve, PC by FFT, undo the shift.

    Each pixel's curve is circularly shifted with ``np.roll`` semantics by
    ``s = round(N/2) - a_med`` (see :func:`depth_from_focus`), its first DFT harmonic is taken
    with ``np.fft.fft`` in float64, ``d = (-angle(H_1) N / (2 pi)) mod N`` and ``d - s`` is
    returned. Slow; not for production use.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume, as for :func:`depth_from_focus`.
    median_size : int, keyword-only
        Odd median-filter size. Default 11.

    Returns
    -------
    (H, W) ndarray of float64
        Depth in fractional level units.
    """
    median_size = _check_median_size(median_size)
    vol = _check_volume(volume)
    if not np.isfinite(vol).all():
        _raise_not_finite(vol)
    n = vol.shape[0]
    s = _spc_shift(vol, median_size)
    k = np.arange(n).reshape(n, 1, 1)
    rolled = np.take_along_axis(vol, (k - s[None]) % n, axis=0)  # rolled[k] = y[k - s]
    h1 = np.fft.fft(rolled.astype(np.float64), axis=0)[1]
    d = np.mod(-np.angle(h1) * n / (2.0 * math.pi), n)
    return d - s


def levels_to_height(depth_levels: np.ndarray, *, focus_heights_um: np.ndarray) -> np.ndarray:
    """Map fractional focus levels to heights by piecewise-linear interpolation.

    Level ``k`` maps to ``focus_heights_um[k]``; between levels the table is interpolated
    linearly, beyond both ends it is extrapolated linearly with the first / last segment.

    Parameters
    ----------
    depth_levels : ndarray of float, any shape
        Depth in fractional level units; NaN stays NaN.
    focus_heights_um : (N,) array_like of float
        Height in focus at each level, µm; N >= 2, finite, strictly increasing or strictly
        decreasing.

    Returns
    -------
    ndarray of float32
        Heights in µm, same shape as ``depth_levels`` (computed in float64).

    Raises
    ------
    ValueError
        If the table is not 1-D with at least 2 finite, strictly monotonic values.
    """
    table = np.asarray(focus_heights_um, dtype=np.float64)
    if table.ndim != 1 or table.size < 2:
        raise ValueError(
            f"focus_heights_um must be 1-D with at least 2 values, got shape {table.shape}"
        )
    if not np.isfinite(table).all():
        raise ValueError("focus_heights_um must be finite")
    step = np.diff(table)
    if not ((step > 0).all() or (step < 0).all()):
        raise ValueError("focus_heights_um must be strictly monotonic")
    d = np.asarray(depth_levels, dtype=np.float64)
    finite = np.isfinite(d)
    i = np.clip(np.floor(np.where(finite, d, 0.0)), 0, table.size - 2).astype(np.intp)
    height = table[i] + (d - i) * step[i]
    return height.astype(np.float32)


def levels_from_heights(height_um: np.ndarray, *, focus_heights_um: np.ndarray
                        ) -> np.ndarray:
    """Heights to fractional focus levels: the inverse of :func:`levels_to_height`.

    Parameters
    ----------
    height_um : ndarray of float, any shape
        Heights, µm (NaN stays NaN).
    focus_heights_um : (N,) array_like of float
        Height in focus at each level, µm, strictly monotonic.

    Returns
    -------
    ndarray of float64
        Levels, piecewise linear, extrapolated beyond both ends with the end segments.
    """
    table = np.asarray(focus_heights_um, dtype=np.float64)
    if table.ndim != 1 or table.size < 2:
        raise ValueError(f"focus_heights_um must be 1-D with at least 2 values, got shape "
                         f"{table.shape}")
    step = np.diff(table)
    if not ((step > 0).all() or (step < 0).all()):
        raise ValueError("focus_heights_um must be strictly monotonic")
    if step[0] < 0:
        table, step = table[::-1], -step[::-1]
        k = np.arange(table.size, dtype=np.float64)[::-1]
    else:
        k = np.arange(table.size, dtype=np.float64)
    z = np.asarray(height_um, dtype=np.float64)
    i = np.clip(np.searchsorted(table, z, side="right") - 1, 0, table.size - 2)
    slope = (k[i + 1] - k[i]) / step[i]
    return k[i] + (z - table[i]) * slope


def all_in_focus(stack: np.ndarray, volume: np.ndarray) -> np.ndarray:
    """All-in-focus image: each pixel's intensity from the level where it is sharpest.

    Parameters
    ----------
    stack : (N, H, W) ndarray
        Image stack, any dtype.
    volume : (N, H, W) ndarray of float
        Its focus volume.

    Returns
    -------
    (H, W) ndarray, dtype of ``stack``
        ``stack[argmax_k volume[k], row, col]`` (first maximum on ties).

    Raises
    ------
    ValueError
        If the shapes differ or are not 3-D.
    """
    stack = np.asarray(stack)
    volume = np.asarray(volume)
    if stack.ndim != 3 or stack.shape != volume.shape:
        raise ValueError(
            f"stack and volume must both be (N, H, W) of the same shape, "
            f"got {stack.shape} and {volume.shape}"
        )
    a = _argmax(volume)
    return np.take_along_axis(stack, a[None], axis=0)[0]
